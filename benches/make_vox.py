#!/usr/bin/env python3
"""Write a deterministic MagicaVoxel model for `brickworld bench lod`:
a level-5 Menger sponge, 243^3 voxels (3.2 M solid), coloured by height
band, so that far views are full of sub-pixel holes (the case level of
detail is for).

    python3 benches/make_vox.py /tmp/sponge.vox
    brickworld bench lod --scene vox:/tmp/sponge.vox --json docs/bench/lod_vox.json

No dependencies beyond the standard library (numpy is not needed).
"""
import struct
import sys

N = 243  # 3^5


def solid(x, y, z):
    while x or y or z:
        if (x % 3 == 1) + (y % 3 == 1) + (z % 3 == 1) >= 2:
            return False
        x, y, z = x // 3, y // 3, z // 3
    return True


def chunk(tag, content, children=b""):
    return tag + struct.pack("<II", len(content), len(children)) + content + children


def main(path):
    xyzi = bytearray()
    count = 0
    for z in range(N):  # MagicaVoxel is Z-up
        colour = 1 + (z * 6) // N  # six height bands
        for y in range(N):
            for x in range(N):
                if solid(x, y, z):
                    xyzi += bytes((x, y, z, colour))
                    count += 1
    palette = bytearray()
    bands = [(196, 92, 60), (222, 160, 72), (120, 168, 80), (64, 140, 160), (96, 96, 180), (200, 200, 210)]
    for i in range(256):
        r, g, b = bands[i % 6] if i < 6 else (128, 128, 128)
        palette += bytes((r, g, b, 255))
    body = chunk(b"SIZE", struct.pack("<III", N, N, N))
    body += chunk(b"XYZI", struct.pack("<I", count) + bytes(xyzi))
    body += chunk(b"RGBA", bytes(palette))
    data = b"VOX " + struct.pack("<I", 150) + chunk(b"MAIN", b"", body)
    with open(path, "wb") as f:
        f.write(data)
    print(f"{path}: {N}^3 Menger sponge, {count} voxels, {len(data)} bytes")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "sponge.vox")
