"""How far apart the views of each capture measure in exposure and white balance (`data.camera_spread`),
at several thresholds of matched points a pair of views needs to count: the figures behind
`train.tone_choice`'s thresholds and `camera_spread.MIN_MATCHES` (README beside this script).

Usage: python benchmarks/studies/tonemap_static/spread.py CAPTURE... [--min-matches 15 10 8]
A capture is any folder `train` reads; every view of it is compared.
"""

from __future__ import annotations

import argparse

from hdrplenoxels.data import camera_spread as spread_module
from hdrplenoxels.data import load_scene


def _stops(value: float | None) -> str:
    return "cannot tell" if value is None else f"{value:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("captures", nargs="+")
    parser.add_argument("--min-matches", type=int, nargs="+", default=[spread_module.MIN_MATCHES])
    args = parser.parse_args()
    print("| capture | views | min matches | exposure | white balance | pairs measured / compared |")
    print("|---|---:|---:|---:|---:|---:|")
    for path in args.captures:
        scene = load_scene(path)
        views = list(range(len(scene.images)))
        for least in args.min_matches:
            spread_module.MIN_MATCHES = least
            s = spread_module.camera_spread(scene, views)
            print(
                f"| {path} | {len(views)} | {least} | {_stops(s.exposure_stops)} | "
                f"{_stops(s.white_balance_stops)} | {s.pairs} / {s.compared} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
