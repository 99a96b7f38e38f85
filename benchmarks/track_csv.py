"""Write a data set split's windows as an ``immnet track`` CSV (``track_id,t,x,y,z``, one row per scan), the input of
benchmarks/bench_default.sh (BENCHMARKS.md "The default tracker against a filter").

Run:  .venv/bin/python benchmarks/track_csv.py SPLIT_DIR OUT.csv [--first N]
e.g. the 1 s real flights' validation windows: ``immnet data adsb --out DIR/quickstart-1s --splits 0.7,0.15,0.15 --seed 0
--samples collections/quickstart``, then ``benchmarks/track_csv.py DIR/quickstart-1s/val val-1s.csv``."""

from __future__ import annotations

import argparse

from immnet import keys
from immnet.data.storage import load_dataset


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("split", help="a data set split's folder (immnet data adsb/generate --out DIR: DIR/val)")
    p.add_argument("out", help="the CSV to write")
    p.add_argument("--first", type=int, default=None, help="only the first N windows (default: all)")
    args = p.parse_args()
    data, _ = load_dataset(args.split)
    z, t = data[keys.MEASUREMENTS].double().numpy(), data[keys.TIME].numpy()
    n = len(z) if args.first is None else min(args.first, len(z))
    with open(args.out, "x") as f:
        f.write("track_id,t,x,y,z\n")
        for i in range(n):
            for k in range(z.shape[1]):
                f.write(f"w{i},{t[i, k]:.3f},{z[i, k, 0]:.3f},{z[i, k, 1]:.3f},{z[i, k, 2]:.3f}\n")
    print(f"{args.out}: {n} tracks, {n * z.shape[1]} rows")


if __name__ == "__main__":
    main()
