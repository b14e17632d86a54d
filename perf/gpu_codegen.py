"""Ahead-of-time CUDA builds of every Warp kernel module, and what each kernel needs on the GPU.

`python -m perf.gpu_codegen [--arch 86 87] [--json OUT] [--md OUT]` builds every Warp module of kernels/_warp/
with Warp's bundled NVRTC for each architecture (no GPU or driver needed: `wp.compile_aot_module`) and reads
from each cubin, per kernel: registers per thread, stack frame (local memory: spills and local arrays, bytes per
thread) and static shared memory; from those, the occupancy of its launch (256 threads per block, Warp's
default, unless the kernel's file lists another in `GPU_BLOCKS = {kernel name: threads}`) on an sm_86 / sm_87
multiprocessor. tests/test_gpu_codegen.py builds the same modules; docs/gpu.md has the table.

Modules: the module of every wp.Kernel defined in a kernels/_warp/*.py file, plus kernels made by factories,
which a file lists with a function `aot_kernels()` -> {label: kernel} (kernels/_warp/icp_reduce.py: the four reduction
specialisations). A file that sets `CPU_ONLY = True` is left out (kernels/_warp/raster_cpu.py: vector code for the
CPU, never launched on CUDA).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import struct
import sys
import tempfile
import time
from pathlib import Path

ARCHS = (86, 87)  # RTX 30xx (the papers' desktop GPUs), Jetson Orin
WARP_BLOCK = 256  # wp.launch's default block_dim, used by every kernel here
# Per-multiprocessor limits of compute capability 8.6 and 8.7 (CUDA C Programming Guide, table of technical
# specifications): 64 K 32-bit registers, 48 resident warps, 16 resident blocks, 255 registers per thread.
SM_REGS, SM_WARPS, SM_BLOCKS, REG_ALLOC = 65536, 48, 16, 256

_EIATTR_FRAME_SIZE, _EIATTR_REGCOUNT = 0x11, 0x2F


def warp_modules() -> dict:
    """name -> warp Module for every kernel module of kernels/_warp (importing them; Warp is initialised).
    Factory-made modules get the label their file gives them in `aot_kernels()` (kept in LABELS)."""
    import warp as wp

    import swarmsplat.kernels._warp as pkg

    wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
    wp.init()
    found: dict = {}
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        mod = importlib.import_module(f"{pkg.__name__}.{info.name}")
        if getattr(mod, "CPU_ONLY", False):
            continue
        kernels = [v for v in vars(mod).values() if isinstance(v, wp.Kernel)]
        for label, k in getattr(mod, "aot_kernels", dict)().items():
            LABELS[k.module.name] = f"{info.name}.{label}"
            kernels.append(k)
        for k in kernels:
            found.setdefault(k.module.name, k.module)
            BLOCKS[k.module.name] = getattr(mod, "GPU_BLOCKS", {})
    return found


LABELS: dict = {}  # module name -> label of a factory-made kernel module
BLOCKS: dict = {}  # module name -> {kernel name: CUDA threads per block} of the file that defines it


def build(module, arch: int, out_dir: str | Path) -> Path:
    """The cubin of one Warp module for sm_<arch>, written under out_dir; raises what Warp raises."""
    import warp as wp

    paths = wp.compile_aot_module(module, arch=arch, module_dir=str(out_dir), use_ptx=False)
    cubins = [Path(p) for p in paths if str(p).endswith(".cubin")]
    if not cubins:
        raise RuntimeError(f"Warp built no cubin for {module.name} sm_{arch}: {paths}")
    return cubins[0]


def cubin_resources(data: bytes) -> dict:
    """kernel symbol -> {"registers", "frame_bytes", "shared_bytes"} from a CUDA cubin (ELF64).

    Registers and frame size are the EIATTR_REGCOUNT / EIATTR_FRAME_SIZE attributes of the `.nv.info` section
    (format byte, attribute byte, u16 size, then the kernel's symbol index and a u32 value); static shared
    memory is the size of the kernel's `.nv.shared.<name>` section.
    """
    if data[:4] != b"\x7fELF" or data[4] != 2:
        raise ValueError("not an ELF64 cubin")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    sections = []
    for i in range(shnum):
        name, typ, _flags, _addr, off, size, link, _info, _align, entsize = struct.unpack_from(
            "<IIQQQQIIQQ", data, shoff + i * shentsize)
        sections.append((name, typ, off, size, link, entsize))
    strtab_off = sections[shstrndx][2]

    def sname(off: int, base: int) -> str:
        return data[base + off:data.index(b"\0", base + off)].decode()

    named = {sname(s[0], strtab_off): s for s in sections}
    symtab = named[".symtab"]
    sym_str = sections[symtab[4]][2]
    symbols = [sname(struct.unpack_from("<I", data, symtab[2] + k * symtab[5])[0], sym_str)
               for k in range(symtab[3] // symtab[5])]
    out: dict = {}
    for sec_name, (_, _, off, size, _, _) in named.items():
        if sec_name == ".nv.info" or sec_name.startswith(".nv.info."):
            p = off
            while p + 4 <= off + size:
                fmt, attr, n = struct.unpack_from("<BBH", data, p)
                payload = n if fmt == 4 else 0  # EIFMT_SVAL carries n bytes; other formats hold a value in n
                if fmt == 4 and attr in (_EIATTR_REGCOUNT, _EIATTR_FRAME_SIZE) and n >= 8:
                    sym, value = struct.unpack_from("<II", data, p + 4)
                    key = "registers" if attr == _EIATTR_REGCOUNT else "frame_bytes"
                    out.setdefault(symbols[sym], {})[key] = value
                p += 4 + payload
    for sec_name, (_, _, _, size, _, _) in named.items():
        if sec_name.startswith(".nv.shared.") and sec_name[len(".nv.shared."):] in out:
            out[sec_name[len(".nv.shared."):]]["shared_bytes"] = size
    for v in out.values():
        v.setdefault("registers", 0)
        v.setdefault("frame_bytes", 0)
        v.setdefault("shared_bytes", 0)
    return {k: v for k, v in out.items() if k.endswith("_cuda_kernel_forward")}


def occupancy(registers: int, block: int = WARP_BLOCK) -> float:
    """Resident warps / 48 of one sm_86 / sm_87 multiprocessor for `block` threads per block, by registers."""
    warps_per_block = (block + 31) // 32
    regs_per_warp = -(-max(registers, 1) * 32 // REG_ALLOC) * REG_ALLOC
    blocks = min(SM_BLOCKS, SM_REGS // (regs_per_warp * warps_per_block), SM_WARPS // warps_per_block)
    return blocks * warps_per_block / SM_WARPS


def kernel_label(module_name: str, symbol: str) -> str:
    """`icp._moments` from module `kernels._warp.icp` and symbol `_moments_1a2b3c4_cuda_kernel_forward`."""
    if module_name in LABELS:
        return LABELS[module_name]
    base = re.sub(r"_[0-9a-f]{7,}$", "", symbol[: -len("_cuda_kernel_forward")])
    return f"{module_name.rsplit('.', 1)[-1]}.{base}"


def run(archs=ARCHS) -> dict:
    mods = warp_modules()
    rows, failures = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name, module in mods.items():
            for arch in archs:
                t0 = time.perf_counter()
                try:
                    cubin = build(module, arch, Path(tmp) / f"sm{arch}")
                except Exception as e:  # noqa: BLE001 - reported per module and arch
                    failures.append({"module": name, "arch": arch, "error": str(e).splitlines()[0]})
                    continue
                secs = time.perf_counter() - t0
                for sym, res in sorted(cubin_resources(cubin.read_bytes()).items()):
                    label = kernel_label(name, sym)
                    block = BLOCKS.get(name, {}).get(label.split(".", 1)[1].split("[")[0], WARP_BLOCK)
                    rows.append({"module": name, "kernel": label, "arch": f"sm_{arch}", **res, "block": block,
                                 "occupancy": round(occupancy(res["registers"], block), 3), "build_s": round(secs, 2)})
    return {"modules": sorted(mods), "archs": list(archs), "rows": rows, "failures": failures}


def markdown(res: dict) -> str:
    lines = ["| kernel | arch | registers | stack frame (B) | shared (B) | threads/block | occupancy |",
             "|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['kernel']} | {r['arch']} | {r['registers']} | {r['frame_bytes']} | {r['shared_bytes']} "
                     f"| {r['block']} | {r['occupancy']:.0%} |")
    for f in res["failures"]:
        lines.append(f"| {f['module']} | sm_{f['arch']} | build failed: {f['error']} | | | | |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.gpu_codegen", description=__doc__.splitlines()[0])
    p.add_argument("--arch", type=int, nargs="+", default=list(ARCHS), help="compute capabilities (86 87)")
    p.add_argument("--json", dest="json_out", help="write the table as JSON here")
    p.add_argument("--md", dest="md_out", help="write the Markdown table here")
    args = p.parse_args(argv)
    from .common import write_results

    res = run(args.arch)
    md = markdown(res)
    print(md)
    print(f"[gpu_codegen] {len(res['modules'])} Warp modules x {len(res['archs'])} archs, "
          f"{len(res['failures'])} failed builds", file=sys.stderr)
    write_results(args.json_out, args.md_out, res, md)
    return 1 if res["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
