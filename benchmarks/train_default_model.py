"""Train the default marking model and cluster verifier shipped in ``mapbuilder/data/``.

Renders procedural scenes (seeds 1000 and up) and crops of the west half of
the Karlsruhe Lanelet2 map at 5–20 cm per pixel, samples candidate pixels,
fits the calibrated quadratic-feature linear SVM and writes it as ONNX.
Then renders 160 scenes from the same seeds (larger, up to 1500 px a side),
clusters what that model finds and fits the cluster verifier (gradient-boosted
trees on :data:`mapbuilder.cluster.CONTEXT_FEATURES`, labelled by whether a
cluster's axis lies on paint). :mod:`benchmarks.classifier_quality` and
:mod:`benchmarks.build_quality` test on other seeds (9000 and up) and the east half.

Run: ``.venv/bin/python benchmarks/train_default_model.py [--n 100] [--only pixel|verifier]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from mapbuilder.classify import MarkingModel, default_model_path, context_verifier_path
from mapbuilder.lanelet2 import read_lanelet2
from mapbuilder.train import train_synthetic, train_synthetic_verifier

ROOT = Path(__file__).resolve().parents[1]
KARLSRUHE = ROOT.parent / "shared" / "data" / "karlsruhe-lanelet2" / "mapping_example.osm"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100, help="number of training renders")
    ap.add_argument("--C", type=float, default=0.5, help="SVM regularisation")
    ap.add_argument("--n-verifier", type=int, default=160, help="renders for the verifier")
    ap.add_argument("--out", default=str(default_model_path()))
    ap.add_argument("--verifier-out", default=str(context_verifier_path()))
    ap.add_argument("--only", choices=("pixel", "verifier"), default=None)
    ap.add_argument("--realism", action="store_true",
                    help="add parking lots and orthophoto artefacts to the pixel model's renders")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    lmap = read_lanelet2(KARLSRUHE)
    if args.only != "verifier":
        t0 = time.perf_counter()
        path = train_synthetic(args.out, seeds=range(1000, 1000 + args.n), lanelet_map=lmap,
                               C=args.C, progress=True, realism=args.realism)
        print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB) "
              f"in {time.perf_counter() - t0:.0f} s")
    if args.only != "pixel":
        t0 = time.perf_counter()
        path = train_synthetic_verifier(args.verifier_out, range(1000, 1000 + args.n_verifier),
                                        lanelet_map=lmap, model=MarkingModel(args.out),
                                        progress=True)
        print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB) "
              f"in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
