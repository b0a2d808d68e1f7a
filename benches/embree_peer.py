#!/usr/bin/env python3
"""Peer benchmark: brickworld's CPU brickmap tracer against Embree 4 on the
blocky triangle mesh of the same heightmap, the same views, in one run.

Install (once):   pip install embreex numpy
Run:              python3 benches/embree_peer.py --json docs/bench/embree_peer.json

What it does:
1. Writes a deterministic heightmap (8-bit PNG, SIZE x SIZE, fBm of value
   noise) to a temporary directory.
2. Runs `brickworld bench tracers --scene heightmap:FILE --threads 1` (the
   brickmap tracer on one thread, the bench's three default views at
   WIDTH x HEIGHT) and reads each view's camera and Mrays/s from its JSON.
3. Builds the blocky triangle mesh of the same heightmap (a quad on top of
   every column, walls wherever a neighbour is lower, the outside counting
   as height 0), in the same voxel units.
4. Traces the same primary rays (the pinhole camera of src/trace/camera.rs,
   pixel centres) with Embree 4 through embreex's `EmbreeScene.run`, which
   calls rtcIntersect1 once per ray on one thread, and times it (the BVH
   build is timed separately, as our scene build is).
5. Reports Mrays/s for both, their ratio, and the hit fractions (a check
   that both traced the same scene and rays). Two ratios: our rendered
   frames (rays made, traced, shaded and written to an image) against
   Embree's intersections, and our hits alone (rays made and traced, the
   hit's distance, voxel, normal and material kept; nothing shaded)
   against the same: Embree's rtcIntersect1 returns a distance, a
   primitive and a normal, and its rays are made before its clock starts.

Embree and brickworld are timed in the same process tree, one after the
other, on the same machine, so the ratio is fair to within the machine's
run-to-run noise (about 10 % here).
"""

import argparse
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
import zlib

try:
    import numpy as np
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
except ImportError as e:  # pragma: no cover - a setup message
    sys.exit(f"error: {e}; install the peer's dependencies with: pip install embreex numpy")


def heightmap(size, seed):
    """fBm of bilinear value noise, 8-bit heights in 1..255."""
    rng = np.random.default_rng(seed)
    h = np.zeros((size, size))
    amp, total = 1.0, 0.0
    cells = 4
    while cells <= size // 2:
        grid = rng.random((cells + 1, cells + 1))
        t = np.linspace(0, cells, size, endpoint=False)
        i = t.astype(int)
        f = t - i
        f = f * f * (3 - 2 * f)
        a = grid[np.ix_(i, i)]
        b = grid[np.ix_(i + 1, i)]
        c = grid[np.ix_(i, i + 1)]
        d = grid[np.ix_(i + 1, i + 1)]
        fz, fx = f[:, None], f[None, :]
        h += amp * (a * (1 - fz) * (1 - fx) + b * fz * (1 - fx) + c * (1 - fz) * fx + d * fz * fx)
        total += amp
        amp *= 0.5
        cells *= 2
    h /= total
    h = (h - h.min()) / (h.max() - h.min())
    return (1 + h ** 1.6 * 254).astype(np.uint8)


def write_png(path, img):
    """An 8-bit grayscale PNG (no dependency beyond zlib)."""
    hgt, wid = img.shape
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(hgt))

    def chunk(kind, data):
        c = struct.pack(">I", len(data)) + kind + data
        return c + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", wid, hgt, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6))
    png += chunk(b"IEND", b"")
    with open(path, "wb") as f:
        f.write(png)


def blocky_mesh(h):
    """Vertices (N, 3) float32 and triangles (M, 3) uint32 of the columns:
    pixel (u, v) = h is the column x = u, z = v, solid for 0 <= y < h."""
    h = h.astype(np.float32)
    n = h.shape[0]
    quads = []
    # Tops: pixel row v is z, column u is x.
    v, u = np.nonzero(h > 0)
    y = h[v, u]
    quads.append(np.stack([
        np.stack([u, y, v], 1), np.stack([u + 1, y, v], 1),
        np.stack([u + 1, y, v + 1], 1), np.stack([u, y, v + 1], 1)], 1))
    padded = np.pad(h, 1)
    # Walls between (u, v) and (u + 1, v), including the outside (height 0).
    a, b = padded[1:-1, :-1], padded[1:-1, 1:]
    v, u = np.nonzero(a != b)
    lo, hi = np.minimum(a, b)[v, u], np.maximum(a, b)[v, u]
    x = u.astype(np.float32)  # plane x = u (between padded columns u-1 and u)
    quads.append(np.stack([
        np.stack([x, lo, v], 1), np.stack([x, hi, v], 1),
        np.stack([x, hi, v + 1], 1), np.stack([x, lo, v + 1], 1)], 1))
    # Walls between (u, v) and (u, v + 1).
    a, b = padded[:-1, 1:-1], padded[1:, 1:-1]
    v, u = np.nonzero(a != b)
    lo, hi = np.minimum(a, b)[v, u], np.maximum(a, b)[v, u]
    z = v.astype(np.float32)
    quads.append(np.stack([
        np.stack([u, lo, z], 1), np.stack([u, hi, z], 1),
        np.stack([u + 1, hi, z], 1), np.stack([u + 1, lo, z], 1)], 1))
    q = np.concatenate(quads).astype(np.float32)
    verts = q.reshape(-1, 3)
    base = np.arange(len(q), dtype=np.uint32)[:, None] * 4
    tris = np.concatenate([base + np.array([0, 1, 2], np.uint32),
                           base + np.array([0, 2, 3], np.uint32)])
    assert n > 0
    return verts, tris


def rays(view, width, height):
    """Origins and directions of the pinhole camera (src/trace/camera.rs)."""
    eye = np.array(view["eye"], np.float64)
    target = np.array(view["target"], np.float64)
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    up = np.cross(r, f)
    t = np.tan(np.radians(view["fov"]) * 0.5)
    i = (np.arange(width) + 0.5) / width * 2 - 1
    j = 1 - (np.arange(height) + 0.5) / height * 2
    a = (i * t * width / height)[None, :, None]
    b = (j * t)[:, None, None]
    d = f + a * r + b * up
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    d = d.reshape(-1, 3).astype(np.float32)
    o = np.broadcast_to(eye.astype(np.float32), d.shape).copy()
    return o, d


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=1024, help="heightmap side in pixels (voxels)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--width", type=int, default=1024)
    p.add_argument("--height", type=int, default=768)
    p.add_argument("--brickworld", default="target/release/brickworld")
    p.add_argument("--json", required=True, help="write the results here")
    a = p.parse_args()
    if not (64 <= a.size <= 8192):
        sys.exit(f"error: --size {a.size} is outside 64..=8192")
    if not os.path.isfile(a.brickworld):
        sys.exit(f"error: {a.brickworld} not found; build it with cargo build --release")
    tmp = tempfile.mkdtemp(prefix="embree-peer-")
    png = os.path.join(tmp, "h.png")
    hm = heightmap(a.size, a.seed)
    write_png(png, hm)
    ours_json = os.path.join(tmp, "ours.json")
    cmd = [a.brickworld, "bench", "tracers", "--scene", f"heightmap:{png}", "--threads", "1",
           "--width", str(a.width), "--height", str(a.height), "--dense-limit-mib", "1",
           "--json", ours_json]
    print("brickworld:", " ".join(cmd), file=sys.stderr)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    ours = json.load(open(ours_json))
    bm = next(s for s in ours["structures"] if s["name"] == "brickmap")
    t0 = time.perf_counter()
    verts, tris = blocky_mesh(hm)
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, verts, tris)
    # The BVH is built on the first query: time it with one ray.
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
    build_s = time.perf_counter() - t0
    views = []
    for k, view in enumerate(ours["views"]):
        o, d = rays(view, a.width, a.height)
        best = None
        for _ in range(3):
            t = time.perf_counter()
            ids = scene.run(o, d)
            s = time.perf_counter() - t
            best = s if best is None else min(best, s)
        embree = len(o) / best / 1e6
        mine = bm["view_mrays_per_s"][k]
        hits = ours["brickmap_hits_only"]["view_mrays_per_s"][k]
        views.append({
            "view": k,
            "embree_mrays_per_s": embree,
            "brickmap_mrays_per_s": mine,
            "ratio": mine / embree,
            "brickmap_hits_only_mrays_per_s": hits,
            "hits_only_ratio": hits / embree,
            "embree_hit_fraction": float(np.mean(ids >= 0)),
        })
        print(f"view {k}: brickmap {mine:.2f} Mrays/s rendered, {hits:.2f} hits alone; "
              f"Embree {embree:.2f} Mrays/s; ratio {mine / embree:.2f} rendered, "
              f"{hits / embree:.2f} hits alone", file=sys.stderr)
    out = {
        "heightmap": {"size": a.size, "seed": a.seed, "max_height": int(hm.max())},
        "width": a.width,
        "height": a.height,
        "threads": 1,
        "embree": {"triangles": int(len(tris)), "build_s": build_s,
                   "binding": "embreex (Embree 4), EmbreeScene.run: rtcIntersect1 per ray"},
        "brickmap": {"build_s": bm["build_s"], "hit_fraction": bm["hit_fraction"]},
        "views": views,
        "mean_ratio": sum(v["ratio"] for v in views) / len(views),
        "mean_hits_only_ratio": sum(v["hits_only_ratio"] for v in views) / len(views),
    }
    # Both traced the same scene and rays: brickworld reports the mean hit
    # fraction over the views.
    mean_hits = sum(v["embree_hit_fraction"] for v in views) / len(views)
    out["embree"]["mean_hit_fraction"] = mean_hits
    if abs(mean_hits - bm["hit_fraction"]) > 0.01:
        sys.exit(f"error: hit fractions differ (Embree {mean_hits:.4f}, brickmap "
                 f"{bm['hit_fraction']:.4f}): the mesh or the rays do not match the voxels")
    with open(a.json, "w") as f:
        json.dump(out, f, indent=2)
    print(f"mean ratio brickmap / Embree: {out['mean_ratio']:.2f} rendered (shaded frames), "
          f"{out['mean_hits_only_ratio']:.2f} hits alone -> {a.json}", file=sys.stderr)


if __name__ == "__main__":
    main()
