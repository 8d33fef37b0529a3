"""A process that writes history at full speed until it is killed (run by test_crash.py).

Usage: python writer.py DB_PATH. It saves learned limits first and says so on
stdout ("limits saved") once they are on disk, then adds revolutions as fast as
the loop turns, in batches between which it yields a little so that the writer
thread commits continuously.
"""

import sys
import time
from pathlib import Path

from millsense.daemon.history import HistoryStore


def main() -> None:
    store = HistoryStore(Path(sys.argv[1]), machine="m1")
    store.start()
    store.save_limits("1234/12/3", {"state": "active", "mean_nm": [1.0, 2.0, 3.0]})
    if not store.flush(30):
        sys.exit("limits not flushed")
    print("limits saved", flush=True)
    rev = 0
    t0 = time.time()
    while True:
        for _ in range(200):
            store.add_revolution({"machine": "m1", "rev": rev, "t": t0 + rev * 0.1, "torque_nm": 4.0 + rev % 7,
                                  "spindle_rpm": 600.0, "tool": 12, "program": 1234, "operation": 3,
                                  "cutting": True, "valid": True})
            rev += 1
        time.sleep(0.002)


if __name__ == "__main__":
    main()
