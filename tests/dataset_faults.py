"""Fault injection for the dataset tests, kept out of the product: run `lsd3d-usd dataset`
in this process and SIGKILL it (no cleanup, as kill -9) when the nuScenes writer is handed
the first sample after its Nth keyframe.

    python tests/dataset_faults.py N dataset SCENE -o DIR ...
"""
import os
import signal
import sys


def main(n: int, argv: list) -> int:
    from lsd3d_usd.datasets import nuscenes
    write = nuscenes.NuScenesWriter.write
    seen = [0]

    def dying_write(self, s):
        if seen[0] >= n:
            os.kill(os.getpid(), signal.SIGKILL)
        write(self, s)
        seen[0] += int(s.keyframe)

    nuscenes.NuScenesWriter.write = dying_write
    from lsd3d_usd.cli import main as cli
    return cli(argv)


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), sys.argv[2:]))
