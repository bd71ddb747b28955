"""Run a command and log its whole process tree's RSS and CPU every 2 s, one JSON line per sample.

    .venv/bin/python bench/tree_log.py LOG.jsonl CMD [ARGS...]

For runs that may be killed and resumed (hours-long tiled runs): the log is appended to and flushed at
every sample, so each segment of a resumed run leaves its wall, CPU and peak RSS behind even when the
command itself never reaches the end where it prints its own figures. ``cpu_s`` sums, over every pid
seen, its last user + system time (a process that ends loses at most its last 2 s). The command's output
goes to ``LOG.jsonl.out``. The last line (when the command ends) holds ``done`` (its exit code),
``peak_gb``, ``wall_s`` and ``cpu_s``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import psutil


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    log_path, cmd = sys.argv[1], sys.argv[2:]
    with open(log_path, "a") as out, open(log_path + ".out", "a") as text:
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        last = {"msg": ""}

        def reader():
            for line in p.stdout:
                text.write(line)
                text.flush()
                last["msg"] = line.strip()[-120:]

        threading.Thread(target=reader, daemon=True).start()
        peak, t0, cpu = 0, time.time(), {}
        root = psutil.Process(p.pid)
        out.write(json.dumps({"start": time.strftime("%Y-%m-%dT%H:%M:%S"), "cmd": cmd}) + "\n")
        out.flush()
        while p.poll() is None:
            rss = 0
            try:
                procs = [root] + root.children(recursive=True)
            except psutil.NoSuchProcess:
                break
            for q in procs:
                try:
                    rss += q.memory_info().rss
                    ct = q.cpu_times()
                    cpu[q.pid] = ct.user + ct.system
                except psutil.Error:
                    pass
            rec = {
                "t": round(time.time() - t0, 1),
                "rss_gb": round(rss / 1e9, 3),
                "cpu_s": round(sum(cpu.values()), 1),
                "load": round(psutil.getloadavg()[0], 2),
                "msg": last["msg"],
            }
            if rss > peak:
                peak, rec["peak"] = rss, True
            out.write(json.dumps(rec) + "\n")
            out.flush()
            time.sleep(2)
        out.write(
            json.dumps(
                {
                    "done": p.wait(),
                    "peak_gb": round(peak / 1e9, 3),
                    "wall_s": round(time.time() - t0, 1),
                    "cpu_s": round(sum(cpu.values()), 1),
                    "end": time.strftime("%Y-%m-%dT%H:%M:%S"),
                }
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
