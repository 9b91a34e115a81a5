"""Run every shell command of the user guide, in page order, in one scratch folder.

    python docs/run_guide.py [--keep DIR]

Commands are the ``bash`` code blocks of the pages listed in ``PAGES`` (a block of
several lines is one shell script); they run with ``bash -e`` in a fresh folder, so the
data that one page simulates is there for the next, as a reader following the guide
would have it. Prints each block with its exit code and time, and exits 1 if any failed.
Lines that install packages are skipped (the commands run with the current environment's
``plenoptrack``).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PAGES = ["install.md", "guide/experiment.md", "guide/calibration.md", "guide/locating.md",
         "guide/uncertainty.md", "guide/tracking.md"]
_BLOCK = re.compile(r"^( *)```bash\n(.*?)^ *```", re.S | re.M)


def blocks(page: Path) -> list[str]:
    """The ``bash`` code blocks of a Markdown page, install lines removed."""
    out = []
    for indent, block in _BLOCK.findall(page.read_text()):
        lines = [line[len(indent):] for line in block.splitlines()]
        lines = [line for line in lines
                 if "pip install" not in line and "python3 -m venv" not in line]
        # the install page calls the checkout's venv; use the current environment instead
        lines = [line.replace(".venv/bin/", "") for line in lines]
        if any(line.strip() for line in lines):
            out.append("\n".join(lines))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="run in this folder and keep it")
    args = parser.parse_args()
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for page in PAGES:
            for script in blocks(HERE / page):
                t0 = time.perf_counter()
                done = subprocess.run(["bash", "-e", "-c", script], cwd=work, env=env,
                                      capture_output=True, text=True)
                seconds = time.perf_counter() - t0
                failed += done.returncode != 0
                print(f"--- {page} (exit {done.returncode}, {seconds:.1f} s)\n{script}")
                print(done.stdout[-3000:] + done.stderr[-3000:], flush=True)
    print(f"{failed} block(s) failed")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
