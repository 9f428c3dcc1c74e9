"""Train the CNN cluster verifier shipped as ``mapbuilder/data/cluster_cnn.onnx``.

Renders procedural scenes and crops of the west half of the Karlsruhe
Lanelet2 map (seeds 1000 and up, as :func:`mapbuilder.train.verifier_training_set`),
classifies them with the shipped pixel model, clusters at the pixel threshold
of CNN-verified builds (:data:`mapbuilder.cluster.CNN_PIXEL_THRESHOLD`),
samples an oriented crop around every cluster, labels it paint when its axis
lies on a painted marking, and fits the small CNN of :mod:`mapbuilder.train_cnn`
(PyTorch, CPU). The benchmarks test on other seeds (9000 and up) and the east
half of the map.

It also writes ``tests/data/cluster_cnn_reference.npz``: a few crops and the
torch model's probabilities for them, which the tests compare with what
onnxruntime computes from the exported file.

Needs PyTorch: ``.venv/bin/pip install -e '.[train-cnn]'``.
Run: ``.venv/bin/python benchmarks/train_cluster_cnn.py [--n 360] [--epochs 12]``
(seeded: the same arguments give the same model on the same machine).
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

from mapbuilder.lanelet2 import read_lanelet2

ROOT = Path(__file__).resolve().parents[1]
KARLSRUHE = ROOT.parent / "shared" / "data" / "karlsruhe-lanelet2" / "mapping_example.osm"
OUT = ROOT / "mapbuilder" / "data" / "cluster_cnn.onnx"
REFERENCE = ROOT / "tests" / "data" / "cluster_cnn_reference.npz"


def _crops(job):
    from mapbuilder.classify import MarkingModel
    from mapbuilder.train import crop_training_set

    seeds, model = job
    return crop_training_set(seeds, model=MarkingModel(model) if model else None,
                             lanelet_map=read_lanelet2(KARLSRUHE))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=360, help="training renders (seeds 1000...)")
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--jobs", type=int, default=2,
                    help="processes rendering the training set (the set does not depend on it)")
    ap.add_argument("--model", default=None,
                    help="pixel model whose clusters to learn (default: the shipped one)")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--reference", default=str(REFERENCE))
    ap.add_argument("--data", default=None,
                    help="cache of the rendered crops (.npz): read when present, else written")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    from mapbuilder.train_cnn import export_cnn_onnx, fit_cnn, torch_predict

    t0 = time.perf_counter()
    cache = Path(args.data) if args.data else None
    if cache is not None and cache.exists():
        d = np.load(cache)
        C, S, y = d["C"], d["S"], d["y"]
    else:
        seeds = list(range(1000, 1000 + args.n))
        m = -(-len(seeds) // args.jobs)
        chunks = [seeds[k:k + m] for k in range(0, len(seeds), m)]
        with multiprocessing.get_context("spawn").Pool(len(chunks)) as pool:
            parts = pool.map(_crops, [(c, args.model) for c in chunks])
        C, S, y = (np.concatenate([p[k] for p in parts]) for k in range(3))
        if cache is not None:
            np.savez(cache, C=C, S=S, y=y)
    print(f"{len(y)} clusters ({y.mean():.0%} paint) in {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    net, history = fit_cnn(C, S, y, epochs=args.epochs, seed=args.seed, threads=args.threads,
                           progress=True)
    print(f"trained in {time.perf_counter() - t0:.0f} s; held-out accuracy "
          f"{history[-1]['held_out_acc']:.4f}")
    path = export_cnn_onnx(net, args.out, {
        "lanemap.trained_on": f"synthetic renders, seeds 1000..{999 + args.n}",
        "lanemap.n_clusters": len(y),
        "lanemap.epochs": args.epochs,
        "lanemap.held_out_accuracy": round(history[-1]["held_out_acc"], 4),
    })
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    rng = np.random.default_rng(args.seed)
    pick = np.concatenate([rng.choice(np.flatnonzero(y), 16, replace=False),
                           rng.choice(np.flatnonzero(~y), 16, replace=False)])
    ref_c = C[pick].astype(np.float16)
    ref_s = S[pick].astype(np.float32)
    Path(args.reference).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.reference, crops=ref_c, scalars=ref_s, label=y[pick],
                        torch_probability=torch_predict(net, ref_c.astype(np.float32), ref_s))
    print(f"wrote {args.reference}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
