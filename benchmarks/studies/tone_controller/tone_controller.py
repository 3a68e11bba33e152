"""How well each tone-controller form predicts a view's tone from its rendered radiance, on trained
runs (tone mapping on): every training view left out in turn, the controller fitted to the others'
learned tones, its prediction compared with the view's learned tone (RMS over views and channels,
stops). Where the run's data has EXIF exposures (`exposure_init_ev` in its transforms.json), also each
form's left-out exposure against the EXIF exposure, after removing the mean difference (the gauge),
beside the learned exposures' own error; and the run's saved controller on its test views (the views a
`--holdout full` run never saw) against their EXIF, the gauge taken from the training views.
Test views take no part in any fit.

Usage: python benchmarks/studies/tone_controller/tone_controller.py RUN [RUN ...] [--json F]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from hdrplenoxels.eval.controller_truth import data_folder, truth_scores, truth_stops
from hdrplenoxels.tonemap.controller import FORMS, leave_one_out_error, leave_one_out_predictions
from hdrplenoxels.train.controller_fit import learned_stops, view_readings
from hdrplenoxels.train.model import MODEL_FILE, Model


def exif_evs(model: Model) -> np.ndarray | None:
    """EXIF exposure (stops) per view from the run's transforms.json, or None."""
    path = data_folder(model) / "transforms.json"
    if not path.exists():
        return None
    frames = json.loads(path.read_text()).get("frames", [])
    by_stem = {Path(f["file_path"]).stem: f.get("exposure_init_ev") for f in frames}
    evs = [by_stem.get(Path(n).stem) for n in model.names]
    return None if any(e is None for e in evs) else np.asarray(evs, dtype=np.float64)


def gauge_free_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS of a - b after removing its mean: the two agree up to the gauge's offset."""
    d = a - b
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def measure(run: Path) -> dict:
    model = Model.load(run / MODEL_FILE)
    ids = list(model.train_ids)
    t = time.perf_counter()
    readings = view_readings(model, ids)
    meter_seconds = (time.perf_counter() - t) / len(ids)
    stops = learned_stops(model, ids)
    out = {"run": str(run), "views": len(ids), "render_and_meter_s_per_view": meter_seconds}
    out["loo_rms_stops"] = {form: leave_one_out_error(form, readings, stops) for form in FORMS}
    evs = exif_evs(model)
    if evs is not None:
        exif = evs[ids]
        # A camera's exposure scales radiance up: its gain rises with EV, so the learned exposure
        # (mean log gain, stops) should follow EXIF EV.
        out["exif_rms_stops"] = {"learned": gauge_free_rms(stops.mean(1), exif)}
        for form in FORMS:
            predicted = leave_one_out_predictions(form, readings, stops).mean(1)
            out["exif_rms_stops"][form] = gauge_free_rms(predicted, exif)
        out["exif_range_stops"] = float(exif.max() - exif.min())
        if model.controller is not None and model.test_ids:
            # Unseen views: the saved controller's exposure for each test view's render against its EXIF,
            # the gauge (offset) taken from the training views' learned exposures, never from test views.
            offset = float(np.mean(stops.mean(1) - exif))
            test = list(model.test_ids)
            test_readings = view_readings(model, test)
            predicted = np.array([model.controller.predict_stops(r).mean() for r in test_readings])
            mean_tone = np.full(len(test), stops.mean())
            out["test_exif_rms_stops"] = {
                model.controller.form: float(np.sqrt(np.mean((predicted - offset - evs[test]) ** 2))),
                "mean": float(np.sqrt(np.mean((mean_tone - offset - evs[test]) ** 2))),
            }
    truth = truth_stops(model)
    if truth is not None and model.controller is not None and model.test_ids:
        out["truth"] = truth_scores(model, truth)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    results = []
    for run in args.runs:
        r = measure(run)
        results.append(r)
        loo = ", ".join(f"{f} {v:.3f}" for f, v in r["loo_rms_stops"].items())
        print(f"{run}: {r['views']} training views; leave-one-out RMS (stops): {loo}")
        if "exif_rms_stops" in r:
            exif = ", ".join(f"{f} {v:.3f}" for f, v in r["exif_rms_stops"].items())
            print(f"  exposure vs EXIF ({r['exif_range_stops']:.2f} stops range), RMS past the gauge: {exif}")
        if "test_exif_rms_stops" in r:
            test = ", ".join(f"{f} {v:.3f}" for f, v in r["test_exif_rms_stops"].items())
            print(f"  test views' exposure vs EXIF (gauge from training views), RMS stops: {test}")
        if "truth" in r:
            t = r["truth"]
            print(f"  test views vs their true tones (gauge slope {t['gauge_slope']:.3f}, training views):")
            for name in ("auto", "mean"):
                print(
                    f"    {name}: exposure RMS {t[name + '_exposure_rms_stops']:.3f} stops, white balance "
                    f"{t[name + '_wb_ratio_error']:.3f} (mean of the largest gain-ratio error), "
                    f"PSNR {t[name + '_psnr']:.2f} dB"
                )
            print(f"    true tone: PSNR {t['true_psnr']:.2f} dB")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
