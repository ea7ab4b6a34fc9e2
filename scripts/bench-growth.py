#!/usr/bin/env python3
"""What 10,000 queued jobs cost a `coordinator serve`: its resident memory,
the size of `/metrics` and of `GET /api/v1/jobs`, and the bytes one studio
tab's event stream receives in its first 5 s, then per second over 10 s.

    scripts/bench-growth.py target/release/coordinator [JOBS]

Starts the service (no local workers, so every job stays queued) in a
temporary directory on a free loopback port, submits JOBS (default 10000)
jobs of a 16 x 16 noisy sphere, measures, and stops it by its pid.
"""

import http.client
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def main():
    binary = os.path.abspath(sys.argv[1])
    jobs = int(sys.argv[2]) if len(sys.argv) > 2 else 10000
    scene = (ROOT / "scenes/noisy_sphere.ron").read_text()
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        log = open(os.path.join(tmp, "serve.log"), "w")
        serve = subprocess.Popen(
            [binary, "serve", "--data", os.path.join(tmp, "data"),
             "--listen", f"127.0.0.1:{port}", "--local-workers", "0", "--quiet"],
            cwd=tmp, stdout=log, stderr=log)
        try:
            deadline = time.time() + 60
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), 0.2).close()
                    break
                except OSError:
                    if time.time() > deadline or serve.poll() is not None:
                        raise RuntimeError("the service did not start")
                    time.sleep(0.1)
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            body = json.dumps({"scene": scene, "scene_name": "noisy_sphere.ron",
                               "out": os.path.join(tmp, "out.png"),
                               "width": 16, "height": 16})
            rss_empty = rss_kib(serve.pid)
            start = time.time()
            for _ in range(jobs):
                conn.request("POST", "/api/v1/jobs", body,
                             {"Content-Type": "application/json"})
                r = conn.getresponse()
                r.read()
                if r.status != 201:
                    raise RuntimeError(f"submit: {r.status}")
            submit_s = time.time() - start
            conn.request("GET", "/metrics")
            metrics = conn.getresponse().read()
            conn.request("GET", "/api/v1/jobs")
            listing = conn.getresponse().read()
            # One studio tab: its event stream for 10 s.
            events = socket.create_connection(("127.0.0.1", port), 5)
            events.sendall(f"GET /studio/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                           "Accept: text/event-stream\r\n\r\n".encode())
            def receive(seconds):
                received = 0
                end = time.time() + seconds
                while time.time() < end:
                    events.settimeout(max(0.01, end - time.time()))
                    try:
                        chunk = events.recv(1 << 20)
                    except socket.timeout:
                        break
                    if not chunk:
                        break
                    received += len(chunk)
                return received
            # The first 5 s (the first status event), then 10 s more.
            first = receive(5.0)
            window = 10.0
            received = receive(window)
            events.close()
            rss = rss_kib(serve.pid)
            series = sum(1 for l in metrics.decode().splitlines()
                         if l and not l.startswith("#"))
            print(json.dumps({
                "jobs": jobs,
                "rss_mib_empty": round(rss_empty / 1024, 1),
                "rss_mib": round(rss / 1024, 1),
                "submit_seconds": round(submit_s, 2),
                "metrics_bytes": len(metrics),
                "metrics_series": series,
                "jobs_list_bytes": len(listing),
                "event_bytes_first_5s": first,
                "event_bytes_per_second_after": round(received / window),
            }, indent=1))
        finally:
            serve.send_signal(signal.SIGTERM)
            try:
                serve.wait(30)
            except subprocess.TimeoutExpired:
                serve.kill()
                serve.wait()


if __name__ == "__main__":
    main()
