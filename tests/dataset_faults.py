"""Fault injection for the dataset tests, kept out of the product: run `lsd3d-usd dataset`
in this process and SIGKILL it (no cleanup, as kill -9) when the writer (any built-in format)
is handed the first sample after its Nth keyframe.

    python tests/dataset_faults.py N dataset SCENE -o DIR ...
"""
import os
import signal
import sys


def main(n: int, argv: list) -> int:
    from lsd3d_usd.datasets.writers import WRITERS
    seen = [0]
    for name in ("nuscenes", "kitti", "mcap"):
        cls = WRITERS.get(name)

        def dying_write(self, s, write=cls.write):
            if seen[0] >= n:
                os.kill(os.getpid(), signal.SIGKILL)
            write(self, s)
            seen[0] += int(s.keyframe)

        cls.write = dying_write
    from lsd3d_usd.cli import main as cli
    return cli(argv)


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), sys.argv[2:]))
