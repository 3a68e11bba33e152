"""Everything the open GPU work carries to a device machine, built here in one command from a fresh
checkout, and the device calls that carry it, printed in order (JOURNAL.md, "Checking a GPU").

A device machine reaches no package registry, has no COLMAP, takes at most 64 MiB a call (the working
tree included) and starts bare in every session, whose device time is 15 minutes, start and idle waits
included; so all of this is made here first, and the calls go back to back. Under the git-ignored
`.gpu/`:

    parts/, wheels/, WHEEL_NAME  Warp's wheel in parts and the small wheels the image lacks (gsplat among
                                 them), from ../shared/tools/prepare_gpu_kit.sh (which empties .gpu/ first)
    demo/                        the demo scene (`hdrplenoxels synth demo`: Mitsuba, absent there)
    capture/asclepius            asclepius, every view, at downscale 4 (gpu_check's `capture` section)
    preset/NAME/x1, x2           the preset search's validation kits (`gpu_preset.py kits`)
    peers/a, peers/b             the peers table's PNG kits (`capture_kit.py --reshoots`), two groups
    svox2/                       svox2's `svox2/` folder, from a clone given with --svox2

The captures are processed once into --work (`real_captures.processed`; reused when there).

Usage: python benchmarks/device_kit.py [--only PART ...] [--svox2 CLONE] [--calls]
"""

from __future__ import annotations

import argparse
import functools
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from capture_kit import reshoot_kits
from gpu_preset import CANDIDATES, kit_size, kits, write_kit
from real_captures import DEFAULT_REALDATA, downscale_for, processed

ROOT = Path(__file__).resolve().parent.parent
KIT = ROOT / ".gpu"
TOOL = ROOT.parent / "shared" / "tools" / "prepare_gpu_kit.sh"
WHEELS = ("ninja==1.13.2", "gsplat==1.5.3", "jaxtyping==0.3.11", "wadler-lindig==0.1.8")
CAPTURE = ("asclepius", 4)  # gpu_check's real capture and its downscale (a target of issue 98)
PEER_GROUPS = {"a": ("kermit", "asclepius"), "b": ("brickstamp", "freiburg_office")}
CALL_MIB = 64.0  # what one call carries, the working tree included
COMMAND_CHARS = 2000  # the longest command a call takes
SESSION_S = 900  # a session's device time
START_S = 40  # a machine's start (JOURNAL.md, "Checking a GPU")
PARTS = ("warp", "demo", "capture", "preset", "peers", "svox2")

INSTALL = (
    "cat /tmp/gk/warp.part.* > /tmp/gk/$(cat .gpu/WHEEL_NAME) && rm /tmp/gk/warp.part.* && "
    "python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site /tmp/gk/*.whl "
    ".gpu/wheels/*.whl"
)
ENV = "export PATH=/tmp/site/bin:$PATH PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1"
# The GPU issue's one script of at most 6 minutes: parity, the step per variant from the graph, the demo's
# `balanced` from the graph, the viewer, Nsight Compute over the default step, asclepius, then the
# levels (each kept as it ends); its report is kept on the machine for the next call's winners.
GPU_CHECK = (
    "python3 benchmarks/gpu_check.py --out $OUT --demo-data .gpu/demo --capture-data .gpu/capture/asclepius "
    "--sections env parity step graph viewer ncu capture levels --parity-files test_step_graph.py "
    "test_sync_free_step.py test_kernel_variants.py test_train.py test_optim.py test_crash_safety.py "
    "test_tone_loss.py test_ray_draw.py test_owed_pull.py test_read_rows.py test_mark_touched.py "
    "test_render_parity.py --deadline 360; cp $OUT/gpu_check.json /tmp/gpu_check.json"
)
AGAIN = "python3 benchmarks/graph_step.py --again /tmp/gpu_check.json --json $OUT/step_again.json"
PEERS = "cd benchmarks && python3 peers_table.py --kits ../.gpu/peers/{group}/peer-kits --out $OUT/peers"
RUN_END = (
    "python3 benchmarks/run_end.py .gpu/demo/varying --preset balanced --steps 0 --repeats 1 "
    "--json $OUT/run_end.json"
)
STAGES = "python3 benchmarks/march_stages.py --problem {p} --rays 5000 --json $OUT/stages_{p}.json"
NCU = (
    f"{STAGES.format(p='spike')}; {STAGES.format(p='paper')}; "
    "python3 benchmarks/prior_update.py --rows 23000000 --json $OUT/prior_update.json; "
    "python3 benchmarks/ncu_march.py --out $OUT/ncu --problem spike --rays 5000 --steps 1"
)
SVOX2 = "python3 svox2_peer.py --source ../.gpu/svox2 --out $OUT/svox2.json"
PRESET = (
    "python3 benchmarks/gpu_preset.py run --kits .gpu/preset --out $OUT/preset --results "
    "benchmarks/gpu_preset_results.json --candidates balanced fine fine-tv10 fine-tv100 --deadline 200"
)


@dataclass(frozen=True)
class Call:
    """One device call: what it carries (paths under the checkout) and runs, within `timeout_s`."""

    carry: tuple[str, ...]
    command: str
    timeout_s: int
    why: str


def warp_parts() -> list[str]:
    return sorted(p.relative_to(ROOT).as_posix() for p in (KIT / "parts").glob("warp.part.*"))


def install_calls(then: str, carry: tuple[str, ...], timeout_s: int, why: str) -> list[Call]:
    """Warp's parts a call each, the last with the wheels and `carry`, installing and running `then`."""
    parts = warp_parts()
    calls = [
        Call((p,), f"mkdir -p /tmp/gk && cp {p} /tmp/gk/", 30, "a part of Warp's wheel") for p in parts[:-1]
    ]
    last = f"mkdir -p /tmp/gk && cp {parts[-1]} /tmp/gk/ && {INSTALL} && {ENV} && {then}"
    return calls + [Call((parts[-1], ".gpu/wheels", ".gpu/WHEEL_NAME", *carry), last, timeout_s, why)]


def sessions(svox2: bool) -> list[list[Call]]:
    """The calls of the next device sessions, each list one session's (the machine starts bare in each)."""
    first = install_calls(
        GPU_CHECK,
        (".gpu/demo", ".gpu/capture"),
        420,
        "issue 98: parity on CUDA, the step per variant from the graph, the demo, viewer, ncu, levels",
    )
    first.append(Call((), f"{ENV} && {AGAIN}", 180, "issue 98: the variants that beat the default, again"))
    second = install_calls(
        RUN_END,
        (".gpu/demo",),
        150,
        "issue 98: the end of a run on the machine's disk (the peers' kits do not fit beside Warp's part)",
    )
    for group, deadline in (("a", 300), ("b", 180)):
        names = " and ".join(PEER_GROUPS[group])
        carry = (f".gpu/peers/{group}",)
        command = f"{ENV} && {PEERS.format(group=group)} --deadline {deadline}"
        second.append(Call(carry, command, deadline + 60, f"issue 52: ours and gsplat on {names}"))
    third = install_calls(
        NCU, (), 300, "issue 98: the march's stages and the prior's update timed, Nsight Compute over a step"
    )
    third.append(Call((".gpu/preset",), f"{ENV} && {PRESET}", 300, "issue 52: the GPU preset's candidates"))
    if not svox2:
        return [first, second, third]
    fourth = install_calls(
        f"cd benchmarks && {SVOX2}", (".gpu/svox2",), 420, "issue 98: svox2 on the same GPU"
    )
    return [first, second, third, fourth]


@functools.cache
def tree_mib() -> float:
    """The tracked working tree, which every call carries."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    files = [ROOT / f for f in tracked.decode().split("\0") if f]
    return sum(f.stat().st_size for f in files if f.is_file()) / 2**20


def carried_mib(call: Call) -> float:
    """What `call` carries: its paths and the tracked working tree."""
    paths = [ROOT / c for c in call.carry]
    return tree_mib() + sum(kit_size(p) if p.is_dir() else p.stat().st_size / 2**20 for p in paths)


def check(call: Call) -> float:
    """`call`'s size in MiB; a ValueError if it carries what is missing, more than a call takes, or too
    long a command."""
    missing = [c for c in call.carry if not (ROOT / c).exists()]
    if missing:
        raise ValueError(f"a call carries {', '.join(missing)}, which is not built (run without --calls)")
    mib = carried_mib(call)
    if mib > CALL_MIB:
        raise ValueError(f"a call carries {mib:.1f} MiB, over {CALL_MIB:.0f}: {', '.join(call.carry)}")
    if len(call.command) > COMMAND_CHARS:
        raise ValueError(f"a call's command has {len(call.command)} characters, over {COMMAND_CHARS}")
    return mib


def session_s(calls: list[Call]) -> int:
    """The most device time `calls` can take: their limits and the machine's start."""
    return START_S + sum(c.timeout_s for c in calls)


def print_calls(svox2: bool) -> None:
    for n, calls in enumerate(sessions(svox2), 1):
        if session_s(calls) > SESSION_S:
            raise ValueError(f"session {n}'s calls may take {session_s(calls)} s, over {SESSION_S}")
        print(
            f"\nDevice session {n}, at most {session_s(calls)} s (back to back: the machine goes back idle):"
        )
        for i, call in enumerate(calls, 1):
            mib = check(call)
            print(f"  {i}. {call.why}; carry {list(call.carry)} ({mib:.1f} MiB), timeout_s {call.timeout_s}:")
            print(f"     {call.command}")


def build(part: str, args: argparse.Namespace) -> None:
    def data(name: str) -> Path:
        return processed(name, args.realdata / name / "images", args.work, None)[0]

    if part == "warp":
        if not TOOL.exists():
            sys.exit(f"device_kit: {TOOL} is missing (it is the workplace's, beside the checkout)")
        subprocess.run(["bash", str(TOOL), *WHEELS], cwd=ROOT, check=True)
    elif part == "demo":
        shutil.rmtree(KIT / "demo", ignore_errors=True)
        subprocess.run([sys.executable, "-m", "hdrplenoxels", "synth", "demo", str(KIT / "demo")], check=True)
    elif part == "capture":
        name, downscale = CAPTURE
        write_kit(data(name), KIT / "capture" / name, downscale, 95)
    elif part == "preset":
        names = sorted(c for group in PEER_GROUPS.values() for c in group)
        options = dict(
            realdata=args.realdata, captures=names, work=args.work, processed=None, quality=95, fold=0
        )
        kits(argparse.Namespace(out=KIT / "preset", candidates=list(CANDIDATES), **options))
    elif part == "peers":
        for group, names in PEER_GROUPS.items():
            for name in names:
                d = data(name)
                reshoot_kits(d, KIT / "peers" / group / "peer-kits" / name, downscale_for(d), None)
    elif part == "svox2":
        if args.svox2 is None:
            print("device_kit: svox2 left out (no --svox2 clone given)", flush=True)
            return
        target = KIT / "svox2"
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir(parents=True)
        archive = subprocess.run(
            ["git", "-C", str(args.svox2), "archive", "HEAD", "svox2"], capture_output=True, check=True
        )
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive.stdout, check=True)
    print(f"device_kit: {part} ready", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", choices=PARTS, default=list(PARTS), help="build these parts")
    ap.add_argument("--svox2", type=Path, help="a clone (or bare copy) of svox2's repository")
    ap.add_argument("--realdata", type=Path, default=DEFAULT_REALDATA)
    ap.add_argument("--work", type=Path, default=Path("runs/gpu-preset"), help="processed captures go here")
    ap.add_argument("--calls", action="store_true", help="only print the calls of what is built")
    args = ap.parse_args()
    if not args.calls:
        for part in [p for p in PARTS if p in args.only]:  # warp first: its tool empties .gpu/
            build(part, args)
    print_calls(svox2=(KIT / "svox2").exists())


if __name__ == "__main__":
    main()
