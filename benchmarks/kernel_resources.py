"""Registers and local memory of the training kernels on a CUDA architecture, with no GPU: each kernel
is compiled for it by Warp's ahead-of-time compiler (NVRTC, shipped in Warp's wheel) and its resources
are read from the compiled binary.

A thread's registers decide how many warps a multiprocessor keeps resident (occupancy: what hides
memory latency), and its stack frame (arrays indexed at run time, spilled registers) lives in local
memory, which is device memory (JOURNAL.md, "Kernel resources"). For each kernel and variant
(`kernels.march_funcs.KernelVariant`) it prints registers per thread, frame bytes per thread, resident warps
per multiprocessor and occupancy at the block size the kernel is launched with.

Usage: python benchmarks/kernel_resources.py [--arch 90] [--json kernel_resources.json]
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import tempfile
from pathlib import Path

# What bounds residency on each architecture (CUDA C Programming Guide, "Compute capabilities"):
# registers per multiprocessor, resident warps, resident blocks; registers are given out per warp in
# units of 256.
ARCHES = {
    80: {"registers": 65536, "warps": 64, "blocks": 32},
    86: {"registers": 65536, "warps": 48, "blocks": 16},
    89: {"registers": 65536, "warps": 48, "blocks": 24},
    90: {"registers": 65536, "warps": 64, "blocks": 32},
}
REGISTER_UNIT = 256
WARP = 32
THREAD_BLOCK = 256  # Warp's default block for a kernel launched over threads
LANE_BLOCK = 32  # the lane kernels: a block (one warp) per ray (`kernels.march_kernel.CUDA_LANES`)

# `.nv.info` attributes of a CUDA binary (the ELF section NVIDIA's tools read resource usage from).
_REGCOUNT = 0x2F
_STACK_SIZE = 0x12  # EIATTR_MIN_STACK_SIZE: the thread's frame, local memory
_FORMAT_SIZED = 0x04  # an attribute with a 16-bit size and that many bytes


def elf_sections(data: bytes) -> dict[str, bytes]:
    """The sections of a 64-bit little-endian ELF file by name. Written here because no maintained
    Python library reads a CUDA binary's resource attributes, and the ELF part is 15 lines."""
    if data[:4] != b"\x7fELF" or data[4] != 2:
        raise ValueError("not a 64-bit ELF file")
    (table,) = struct.unpack_from("<Q", data, 0x28)
    entry_size, count, names_index = struct.unpack_from("<HHH", data, 0x3A)
    headers = [struct.unpack_from("<IIQQQQ", data, table + i * entry_size) for i in range(count)]
    names = headers[names_index][4]
    out = {}
    for name, _type, _flags, _addr, offset, size in headers:
        end = data.index(b"\0", names + name)
        out[data[names + name : end].decode()] = data[offset : offset + size]
    return out


def cubin_resources(data: bytes) -> tuple[int, int]:
    """(registers per thread, frame bytes per thread) of the kernel in a CUDA binary."""
    info = elf_sections(data).get(".nv.info", b"")
    registers = frame = 0
    i = 0
    while i + 4 <= len(info):
        fmt, attribute = info[i], info[i + 1]
        if fmt != _FORMAT_SIZED:
            i += 4  # a 2-byte value follows
            continue
        (size,) = struct.unpack_from("<H", info, i + 2)
        payload = info[i + 4 : i + 4 + size]
        i += 4 + size
        if attribute == _REGCOUNT:
            registers = max(registers, struct.unpack_from("<II", payload)[1])
        elif attribute == _STACK_SIZE:
            frame = max(frame, struct.unpack_from("<II", payload)[1])
    if registers == 0:
        raise ValueError("no register count in the binary's .nv.info")
    return registers, frame


def resident_warps(registers: int, block: int, arch: int) -> int:
    """Warps a multiprocessor of `arch` keeps resident for blocks of `block` threads at `registers`
    registers a thread (shared memory is no bound for these kernels)."""
    limits = ARCHES[arch]
    per_block = math.ceil(block / WARP)
    per_warp = math.ceil(registers * WARP / REGISTER_UNIT) * REGISTER_UNIT
    blocks = min(limits["registers"] // per_warp // per_block, limits["blocks"], limits["warps"] // per_block)
    return blocks * per_block


def compiled_resources(kernel, arch: int, folder: Path) -> tuple[int, int]:
    import warp as wp

    (path,) = wp.compile_aot_module(kernel.module, arch=arch, module_dir=folder, use_ptx=False)
    return cubin_resources(Path(path).read_bytes())


def kernels(levels: int) -> list[tuple[str, str, object, int]]:
    """(kernel, variant, Warp kernel, launch block) for the training kernels: the render kernels at 9 SH
    coefficients per channel for each variant, then the other kernels of a step."""
    from hdrplenoxels.kernels.march_forward import forward_for
    from hdrplenoxels.kernels.march_funcs import GENERAL, KernelVariant
    from hdrplenoxels.kernels.march_lanes import lane_backward_for
    from hdrplenoxels.kernels.march_threads import thread_backward_for

    variants = {
        "general": GENERAL,
        "one box, no features": KernelVariant(1, False, False, False, False),
        f"{levels} levels, background + near": KernelVariant(levels, False, True, True, False),
        "general, 128 registers": KernelVariant(max_registers=128),
        "general, 96 registers": KernelVariant(max_registers=96),
        "general, 64 registers": KernelVariant(max_registers=64),
    }
    out = []
    for name, variant in variants.items():
        out += [
            ("thread forward", name, forward_for(9, 0, variant), THREAD_BLOCK),
            ("thread backward", name, thread_backward_for(9, variant), THREAD_BLOCK),
            ("lane forward", name, forward_for(9, LANE_BLOCK, variant), LANE_BLOCK),
            ("lane backward", name, lane_backward_for(9, LANE_BLOCK, variant), LANE_BLOCK),
        ]
    kept = KernelVariant(rows_from_corners=True)  # the lane backward's rows from the sample's corners
    out.append(
        ("lane backward", "general, rows from corners", lane_backward_for(9, LANE_BLOCK, kept), LANE_BLOCK)
    )
    # the lane kernels' colour sum by warp shuffles, then several rays a block of 32 (lanes x rays)
    for lanes, rays in ((LANE_BLOCK, 1), (16, 2), (8, 4)):
        shuffled = KernelVariant(shuffle_sum=True, rays_per_block=rays)
        name = "general, shuffle sum" + (f", {rays} rays x {lanes}" if rays > 1 else "")
        out += [
            ("lane forward", name, forward_for(9, lanes, shuffled), LANE_BLOCK),
            ("lane backward", name, lane_backward_for(9, lanes, shuffled), LANE_BLOCK),
        ]
    from hdrplenoxels.kernels.background_march import msi_backward_kernel, msi_forward_kernel
    from hdrplenoxels.kernels.march_read_rows import mark_read_rows_kernel
    from hdrplenoxels.kernels.msi_tv_kernel import _msi_tv_grad
    from hdrplenoxels.kernels.occupancy_kernel import _mark_occupied
    from hdrplenoxels.kernels.ray_draw_kernel import _draw_rays
    from hdrplenoxels.kernels.rmsprop_kernel import (
        _flat_kernel,
        _owed_kernel,
        _touched_kernel,
        pay_owed_values,
        stamp_paid_rows,
    )
    from hdrplenoxels.kernels.rmsprop_listed import (
        _listed_touched_kernel,
        list_owing_rows,
        list_touched_rows,
        pay_listed_values,
        stamp_listed_rows,
    )
    from hdrplenoxels.kernels.torch_rmsprop_kernel import _torch_rmsprop
    from hdrplenoxels.kernels.tv_kernel import _tv_kernel
    from hdrplenoxels.tonemap.loss_kernel import _curve_smoothness, _tone_loss

    return out + [
        ("RMSProp, touched rows", "27 SH columns", _touched_kernel(27, 1), THREAD_BLOCK),
        ("RMSProp, touched rows", "27 SH columns, owed pull", _touched_kernel(27, 1, True), THREAD_BLOCK),
        ("RMSProp, touched rows", "listed: rows listed", list_touched_rows, THREAD_BLOCK),
        ("RMSProp, touched rows", "listed: their values", _listed_touched_kernel(False), THREAD_BLOCK),
        (
            "RMSProp, touched rows",
            "listed: their values, owed pull",
            _listed_touched_kernel(True),
            THREAD_BLOCK,
        ),
        ("owed pull paid", "27 SH columns", _owed_kernel(27), THREAD_BLOCK),
        ("owed pull paid", "a thread per value", pay_owed_values, THREAD_BLOCK),
        ("owed pull paid", "rows stamped", stamp_paid_rows, THREAD_BLOCK),
        ("owed pull paid", "listed: rows that owe listed", list_owing_rows, THREAD_BLOCK),
        ("owed pull paid", "listed: their values", pay_listed_values, THREAD_BLOCK),
        ("owed pull paid", "listed: rows stamped", stamp_listed_rows, THREAD_BLOCK),
        ("rows a forward reads", "", mark_read_rows_kernel, THREAD_BLOCK),
        ("RMSProp, flat", "", _flat_kernel(1), THREAD_BLOCK),
        ("TV of sampled cells", "a thread per cell", _tv_kernel(False), THREAD_BLOCK),
        ("TV of sampled cells", "a thread per (cell, channel)", _tv_kernel(True), THREAD_BLOCK),
        ("occupancy marks", "", _mark_occupied, THREAD_BLOCK),
        ("MSI forward", "", msi_forward_kernel, THREAD_BLOCK),
        ("MSI backward", "", msi_backward_kernel, THREAD_BLOCK),
        ("tone loss", "", _tone_loss, THREAD_BLOCK),
        ("curve smoothness", "", _curve_smoothness, THREAD_BLOCK),
        ("ray draw", "", _draw_rays, THREAD_BLOCK),
        ("RMSProp, tone", "", _torch_rmsprop, THREAD_BLOCK),
        ("MSI TV, dense", "", _msi_tv_grad, THREAD_BLOCK),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", type=int, default=90, choices=sorted(ARCHES), help="compute capability x 10")
    ap.add_argument("--levels", type=int, default=6, help="cascade levels of the specialised variant")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    wp.init()
    rows = []
    print(f"sm_{args.arch}: registers and frame (local memory) per thread, resident warps per multiprocessor")
    print(f"{'kernel':24} {'variant':34} {'regs':>5} {'frame B':>8} {'warps':>6} {'occupancy':>9}")
    with tempfile.TemporaryDirectory() as folder:
        for kernel_name, variant, kernel, block in kernels(args.levels):
            try:
                registers, frame = compiled_resources(kernel, args.arch, Path(folder))
            except Exception as err:  # no NVRTC in this Warp: say so rather than guess
                sys.exit(f"could not compile {kernel_name} for sm_{args.arch}: {err}")
            warps = resident_warps(registers, block, args.arch)
            occupancy = warps / ARCHES[args.arch]["warps"]
            rows.append(
                dict(
                    kernel=kernel_name,
                    variant=variant,
                    registers=registers,
                    frame_bytes=frame,
                    block=block,
                    warps=warps,
                    occupancy=occupancy,
                )
            )
            print(
                f"{kernel_name:24} {variant:34} {registers:5d} {frame:8d} {warps:6d} {occupancy:9.1%}",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps({"arch": args.arch, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
