"""Where a command's memory peaks: runs ``graphslam ARGS...`` in this process while a thread samples
the resident set every 10 ms with the main thread's innermost three graphslam frames; prints the
highest RSS seen under each such stack (those above 600 MB), in the order they first appeared.

    python lab/speed/rss_by_stack.py -q survey DIR -o OUT --set optimizer.solver=cholmod --no-picture
"""

from __future__ import annotations

import sys
import threading
import time
import traceback

MIN_KB = 600_000  # stacks below this are not printed


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))


def main(argv: list[str]) -> None:
    main_id = threading.get_ident()
    peak: dict[str, int] = {}

    def sample() -> None:
        while True:
            frame = sys._current_frames().get(main_id)
            stack = [f"{fs.filename.split('graphslam/')[-1]}:{fs.name}"
                     for fs in traceback.extract_stack(frame) if "graphslam/" in fs.filename]
            key = " > ".join(stack[-3:])
            peak[key] = max(peak.get(key, 0), _rss_kb())
            time.sleep(0.01)

    threading.Thread(target=sample, daemon=True).start()
    from graphslam import cli_main

    try:
        cli_main(argv)
    except SystemExit:
        pass
    for key, kb in list(peak.items()):
        if kb > MIN_KB:
            print(f"{kb // 1024:6d} MB  {key}", file=sys.stderr)


if __name__ == "__main__":
    main(sys.argv[1:])
