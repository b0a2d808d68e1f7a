#!/usr/bin/env python3
# /status latency while 200 slow clients trickle their request heads (issue 8).
# Usage: brickworld run --addr 127.0.0.1:PORT & python3 benches/slow_clients.py PORT
import socket, time, threading, json, sys, statistics
addr=("127.0.0.1", int(sys.argv[1]))
stop=False
def slow():
    # A slow client: sends its head one byte every 200 ms, reconnecting when cut off.
    while not stop:
        try:
            s=socket.create_connection(addr, timeout=10)
            for ch in b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a"*10000:
                if stop: break
                s.send(bytes([ch])); time.sleep(0.2)
        except Exception:
            time.sleep(0.1)
ts=[threading.Thread(target=slow, daemon=True) for _ in range(200)]
for t in ts: t.start()
time.sleep(3)
lat=[]
for i in range(1000):
    t0=time.perf_counter()
    s=socket.create_connection(addr, timeout=10)
    # Host names an IP: the engine answers 403 to other names (its
    # DNS-rebinding guard), which this bench must not time.
    s.sendall(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
    data=b""
    while True:
        c=s.recv(65536)
        if not c: break
        data+=c
    s.close()
    lat.append((time.perf_counter()-t0)*1000)
    if not data.startswith(b"HTTP/1.1 200"):
        stop=True
        line=data.split(b"\r\n")[0].decode(errors="replace")
        sys.exit(f"error: /status answered {line!r}, not 200")
    time.sleep(0.01)
stop=True
lat.sort()
print(json.dumps({"slow_clients":200,"requests":len(lat),"p50_ms":round(lat[len(lat)//2],3),"p99_ms":round(lat[int(len(lat)*0.99)],3),"max_ms":round(lat[-1],3)}))
