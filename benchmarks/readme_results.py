"""The README's figures: one committed results file (`docs/results.json`) and the Markdown tables made
from it, which `tests/test_readme_results.py` finds in the README word for word.

`--table-s1 REPORT.json` takes the synthetic scenes' row of each method from a `hdrplenoxels experiment
table-s1` report, `--real RESULTS.json` the real captures' re-shoots from `benchmarks/real_captures.py
--json`, `--demo REPORT.json` the demo's from `make demo`'s `demo_out/report.json`; `--times FILE.json`
merges the three-command times measured by hand (`{"cpu": {...}, "gpu": {...}}`). Each is written into
`docs/results.json` with the date given; then the tables are printed, to paste into README.md.

Usage: python benchmarks/readme_results.py [--table-s1 R.json] [--real R.json] [--demo R.json]
       [--times T.json] [--date YYYY-MM-DD]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results.json"
S1_COLUMNS = ("plenoxels_static", "plenoxels_varying", "ours_varying", "ours_static")
S1_LABELS = {
    "room": "room",
    "objects360": "objects360",
    "extreme": "extreme (a bare bulb: over 12 stops)",
    "courtyard": "courtyard (unbounded: a cascade of boxes)",
    "indoor": "indoor (cameras inside a room)",
    "street": "street (a walk down a street)",
}
REAL_METHODS = ("plenoxels-static", "plenoxels-varying", "ours-varying")


def load() -> dict:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {}


def from_table_s1(report: dict) -> dict:
    """Each scene's right-half PSNR per method, from a table-s1 report."""
    return {
        scene: {m: round(methods[m]["psnr"], 2) for m in S1_COLUMNS if m in methods}
        for scene, methods in report["scenes"].items()
    }


def from_real(rows: list[dict]) -> dict:
    """Each capture's right-half PSNR per re-shoot method (`fast`), from real_captures.py's JSON."""
    out: dict = {}
    for row in rows:
        if row["method"] in REAL_METHODS and row["preset"] == "fast":
            out.setdefault(row["capture"], {})[row["method"]] = round(row["psnr_right"], 2)
    return out


def from_demo(report: dict) -> dict:
    methods = report["scenes"]["demo"]
    return {m: {"psnr": round(v["psnr"], 2), "train_s": round(v["train_s"], 1)} for m, v in methods.items()}


def synthetic_table(results: dict) -> str:
    rows = results["table_s1"]["scenes"]
    lines = [
        "| PSNR (dB) | Plenoxels, one fixed camera | Plenoxels, varying | ours, varying "
        "| ours, one fixed camera (tone mapping forced on) |",
        "|---|---:|---:|---:|---:|",
    ]
    for scene, label in S1_LABELS.items():
        if scene in rows:
            cells = " | ".join(f"{rows[scene][m]:.2f}" for m in S1_COLUMNS)
            lines.append(f"| {label} | {cells} |")
    return "\n".join(lines)


def real_table(results: dict) -> str:
    rows = results["real_reshoots"]["captures"]
    lines = [
        "| PSNR (dB) | Plenoxels, one fixed camera | Plenoxels, varying | ours, varying |",
        "|---|---:|---:|---:|",
    ]
    for capture in sorted(rows):
        cells = " | ".join(f"{rows[capture][m]:.2f}" for m in REAL_METHODS)
        lines.append(f"| {capture} | {cells} |")
    return "\n".join(lines)


def demo_table(results: dict) -> str:
    demo = results["demo"]["methods"]
    names = {
        "plenoxels_static": "Plenoxels, one fixed camera",
        "plenoxels_varying": "Plenoxels, varying camera",
        "ours_varying": "ours, varying camera",
    }
    lines = ["| `make demo` | PSNR (dB) | training |", "|---|---:|---:|"]
    lines += [
        f"| {label} | {demo[m]['psnr']:.2f} | {demo[m]['train_s']:.0f} s |" for m, label in names.items()
    ]
    return "\n".join(lines)


def times_table(results: dict) -> str:
    t = results["three_commands"]
    lines = ["| step | " + " | ".join(c["machine"] for c in t["columns"]) + " |"]
    lines.append("|---|" + "---:|" * len(t["columns"]))
    for step in t["steps"]:
        lines.append(f"| {step} | " + " | ".join(c["seconds"].get(step, "—") for c in t["columns"]) + " |")
    return "\n".join(lines)


TABLES = {"synthetic": synthetic_table, "real": real_table, "demo": demo_table, "times": times_table}


def tables(results: dict) -> dict[str, str]:
    """Every README table the results file has the figures for, by name."""
    keys = {"synthetic": "table_s1", "real": "real_reshoots", "demo": "demo", "times": "three_commands"}
    return {name: make(results) for name, make in TABLES.items() if keys[name] in results}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--table-s1", type=Path)
    parser.add_argument("--real", type=Path)
    parser.add_argument("--demo", type=Path)
    parser.add_argument("--times", type=Path)
    parser.add_argument("--date", default="")
    args = parser.parse_args()
    results = load()
    # results key, the command that measured it, the field its figures go in, how they are read
    sources = {
        "table_s1": ("hdrplenoxels experiment table-s1 OUT --no-lpips", "scenes", from_table_s1),
        "real": (
            "python benchmarks/real_captures.py --presets fast --methods " + " ".join(REAL_METHODS),
            "captures",
            from_real,
        ),
        "demo": ("make demo", "methods", from_demo),
    }
    keys = {"table_s1": "table_s1", "real": "real_reshoots", "demo": "demo"}
    for arg, (command, field, read) in sources.items():
        path = getattr(args, arg)
        if path:
            figures = read(json.loads(path.read_text()))
            results[keys[arg]] = {"command": command, "date": args.date, field: figures}
    if args.times:
        results["three_commands"] = json.loads(args.times.read_text()) | {"date": args.date}
    if any((args.table_s1, args.real, args.demo, args.times)):
        RESULTS.write_text(json.dumps(results, indent=1, ensure_ascii=False) + "\n")
    for name, table in tables(results).items():
        print(f"<!-- {name} -->\n{table}\n")


if __name__ == "__main__":
    main()
