"""Train the default marking model shipped in ``mapbuilder/data/``.

Renders procedural scenes (seeds 1000 and up) and crops of the west half of
the Karlsruhe Lanelet2 map at 5–20 cm per pixel, samples candidate pixels,
fits the calibrated quadratic-feature linear SVM and writes it as ONNX.
:mod:`benchmarks.classifier_quality` tests on other seeds and the east half.

Run: ``.venv/bin/python benchmarks/train_default_model.py [--n 120] [--out PATH]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from mapbuilder.classify import default_model_path
from mapbuilder.lanelet2 import read_lanelet2
from mapbuilder.train import train_synthetic

ROOT = Path(__file__).resolve().parents[1]
KARLSRUHE = ROOT.parent / "shared" / "data" / "karlsruhe-lanelet2" / "mapping_example.osm"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100, help="number of training renders")
    ap.add_argument("--C", type=float, default=0.5, help="SVM regularisation")
    ap.add_argument("--out", default=str(default_model_path()))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.perf_counter()
    lmap = read_lanelet2(KARLSRUHE)
    path = train_synthetic(args.out, seeds=range(1000, 1000 + args.n), lanelet_map=lmap,
                           C=args.C, progress=True)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
