#!/usr/bin/env python3
"""What live viewers cost the engine, and how late frames reach them (issue 12).

Usage: python3 benches/viewer_cost.py [--world worlds/default.toml] [--viewers 3]
       [--phase-s 20] [--rounds 3] [--json docs/bench/viewer_cost.json]

Starts `brickworld run` on the world (default: the embedded default world)
in a temporary state directory, then alternates phases with no viewer and
with N viewers, measuring ticks/s in each from /status. A viewer does what
the page does on the wire: it holds GET /events open, and on every `frame`
event fetches /frame.png, one fetch at a time. Its latency is the time from
the frame's `rendered_unix_ms` (the end of its PNG encoding) to the end of
that fetch, on loopback; the first event of a connection announces an older
frame and is not counted. The viewers run in this process, on the same
machine as the engine: their CPU competes with it, so the cost measured is
an upper bound for viewers on other machines. It does not include a
browser's decoding and drawing (the browser test reports that latency as
seen by the page).
"""
import argparse, json, os, re, shutil, socket, statistics, subprocess, sys, tempfile, threading, time

class Refused(Exception):
    """The engine answered, but not with 200 (a wrong Host gets 403)."""

def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p

def get(addr, path):
    s = socket.create_connection(addr, timeout=10)
    # The engine answers 403 to a Host that is neither an IP nor localhost
    # (its DNS-rebinding guard): name the address it listens on.
    s.sendall(f"GET {path} HTTP/1.1\r\nHost: {addr[0]}:{addr[1]}\r\nConnection: close\r\n\r\n".encode())
    data = b""
    while True:
        c = s.recv(1 << 20)
        if not c: break
        data += c
    s.close()
    head, _, body = data.partition(b"\r\n\r\n")
    if not head.startswith(b"HTTP/1.1 200"):
        line = head.split(b"\r\n")[0].decode(errors="replace")
        raise Refused(f"GET {path}: {line}")
    return head, body

def status(addr):
    return json.loads(get(addr, "/status")[1])

class Viewer(threading.Thread):
    def __init__(self, addr):
        super().__init__(daemon=True)
        self.addr, self.stop, self.lat, self.frames = addr, False, [], 0
    def run(self):
        s = socket.create_connection(self.addr, timeout=30)
        s.sendall(f"GET /events HTTP/1.1\r\nHost: {self.addr[0]}:{self.addr[1]}\r\n\r\n".encode())
        buf, first = b"", True
        while not self.stop:
            try:
                c = s.recv(1 << 16)
            except socket.timeout:
                continue
            if not c: break
            buf += c
            while True:
                m = re.search(rb"event: (\w+)\ndata: (.*)\n\n", buf)
                if not m: break
                buf = buf[m.end():]
                if m.group(1) != b"frame": continue
                f = json.loads(m.group(2))
                get(self.addr, f"/frame.png?seq={f['seq']}")
                self.frames += 1
                if first:
                    first = False
                    continue
                self.lat.append(time.time() * 1000 - f["rendered_unix_ms"])
        s.close()

def ticks_per_s(addr, secs):
    t0, k0 = time.time(), status(addr)["tick"]
    time.sleep(secs)
    return (status(addr)["tick"] - k0) / (time.time() - t0)

def main():
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--brickworld", default="target/release/brickworld")
    a.add_argument("--world", default=None, help="world config (default: the embedded default world)")
    a.add_argument("--viewers", type=int, default=3)
    a.add_argument("--phase-s", type=float, default=20)
    a.add_argument("--rounds", type=int, default=3)
    a.add_argument("--json", default=None)
    o = a.parse_args()
    if not (1 <= o.viewers <= 16): sys.exit("error: --viewers must be 1..=16 (the engine serves 16)")
    if not (1 <= o.rounds <= 100) or not (1 <= o.phase_s <= 3600): sys.exit("error: --rounds 1..=100, --phase-s 1..=3600")
    if not os.path.isfile(o.brickworld): sys.exit(f"error: {o.brickworld} not found; build it with cargo build --release")
    state = tempfile.mkdtemp(prefix="viewer-cost-")
    port = free_port(); addr = ("127.0.0.1", port)
    cmd = [o.brickworld, "run"] + ([o.world] if o.world else []) + ["--state", state, "--addr", f"127.0.0.1:{port}"]
    eng = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t = time.time()
        while True:
            try:
                if status(addr)["frames"] >= 2: break
            except Refused as e: sys.exit(f"error: the engine refused the bench's request: {e}")
            except Exception: pass
            if time.time() - t > 300 or eng.poll() is not None: sys.exit("error: the engine did not start")
            time.sleep(0.2)
        without, with_, lat, frames = [], [], [], 0
        for r in range(o.rounds):
            without.append(ticks_per_s(addr, o.phase_s))
            vs = [Viewer(addr) for _ in range(o.viewers)]
            for v in vs: v.start()
            time.sleep(1)
            with_.append(ticks_per_s(addr, o.phase_s))
            for v in vs: v.stop = True
            for v in vs: v.join(timeout=5); lat += v.lat; frames += v.frames
            print(f"round {r + 1}: {without[-1]:.2f} ticks/s without viewers, {with_[-1]:.2f} with {o.viewers}", file=sys.stderr)
        lat.sort()
        out = {
            "world": o.world or "embedded default", "viewers": o.viewers, "phase_s": o.phase_s, "rounds": o.rounds,
            "ticks_per_s_without": without, "ticks_per_s_with": with_,
            "cost_fraction": 1 - statistics.mean(with_) / statistics.mean(without),
            "frames_fetched": frames,
            "latency_ms": {"n": len(lat), "p50": lat[len(lat) // 2] if lat else None,
                            "p99": lat[int(len(lat) * 0.99)] if lat else None, "max": lat[-1] if lat else None},
        }
        print(json.dumps(out, indent=2))
        if o.json:
            with open(o.json, "w") as f: json.dump(out, f, indent=2)
    finally:
        eng.terminate(); eng.wait(timeout=60)
        shutil.rmtree(state, ignore_errors=True)

if __name__ == "__main__":
    main()
