"""`python -m perf device-check [--device cuda|vulkan|cpu] [--subjects ...] [--no-tests] [--no-bench]
[--real-frames N] [--out F]` (or `make device-check DEVICE=cuda`): everything this project can check on one real
device, in one command.

1. Which backend/device pairs work here (`kernels.devices(run=True)`: each one runs the axpy probe and the device
   self-check, kernels/selfcheck.py).
2. The device's cases of the test suite (`pytest -k <device>`: every `backend`-matrix case on that device — the
   kernels against their twins and finite differences — plus, for cuda, tests/test_gpu_codegen.py and, for
   vulkan, tests/test_vulkan.py), counted from pytest's JUnit XML.
3. A short benchmark (`--quick`) of every perf subject on the device, one subprocess each, so one failing
   subject does not hide the others.
4. Real data on every pair: the first `--real-frames` (60; 0: skip) frames of the shared Redwood sequence through
   `swarmsplat run` on warp-cpu, taichi-cpu and the device's pairs, whose ATE and PSNR must agree with warp-cpu's
   (within 2 % and 0.3 dB: perf/device_agreement.py).
Writes one JSON (default perf/results/device-check-<device>.json): machine, versions, device pairs, test counts
and failures, per-subject results or errors, the real runs. Exit status 1 when a test or a subject failed or the
real runs disagree.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXTRA_TESTS = {"cuda": " or gpu_codegen", "vulkan": "", "cpu": ""}


def versions() -> dict:
    """Warp / Taichi / torch versions, Warp's CUDA toolkit and the CUDA device, where present."""
    out: dict = {}
    try:
        import torch

        out["torch"] = torch.__version__
        if torch.cuda.is_available():
            out["cuda_device"] = torch.cuda.get_device_name(0)
            out["compute_capability"] = "sm_%d%d" % torch.cuda.get_device_capability(0)
    except Exception as e:  # noqa: BLE001 - reported, not fatal
        out["torch_error"] = str(e)
    try:
        import warp as wp

        out["warp"] = wp.config.version
        import warp._src.context as ctx

        wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
        wp.init()
        out["warp_cuda_toolkit"] = ".".join(map(str, ctx.runtime.toolkit_version))
        out["warp_cuda_driver"] = ".".join(map(str, ctx.runtime.driver_version)) if ctx.runtime.driver_version else None
    except Exception as e:  # noqa: BLE001
        out["warp_error"] = str(e)
    try:
        import taichi as ti

        out["taichi"] = ".".join(map(str, ti.__version__))
    except Exception as e:  # noqa: BLE001
        out["taichi_error"] = str(e)
    return out


def run_tests(device: str, timeout: float) -> dict:
    """The device's test cases in a fresh interpreter; counts and failing test ids from the JUnit XML."""
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "junit.xml"
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", device + EXTRA_TESTS[device],
               f"--junitxml={xml}", str(REPO / "tests")]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout, env=_env())
        res = {"command": " ".join(cmd[1:]), "returncode": proc.returncode,
               "seconds": round(time.perf_counter() - t0, 1)}
        if not xml.exists():
            res["error"] = (proc.stdout + proc.stderr)[-2000:]
            return res
        counts = {"passed": 0, "failed": 0, "skipped": 0, "xfailed": 0}
        failures = []
        for case in ET.parse(xml).getroot().iter("testcase"):
            tag = {child.tag for child in case}
            name = f"{case.get('classname')}::{case.get('name')}"
            if tag & {"failure", "error"}:
                counts["failed"] += 1
                failures.append(name)
            elif "skipped" in tag:
                msg = next(c for c in case if c.tag == "skipped").get("type", "")
                counts["xfailed" if "xfail" in msg else "skipped"] += 1
            else:
                counts["passed"] += 1
        res.update(counts=counts, failures=failures, tail=proc.stdout[-1500:])
        return res


def run_bench(device: str, subjects: list[str], timeout: float) -> dict:
    """`python -m perf SUBJECT --quick --device DEVICE` for each subject; its JSON, or its error."""
    out = {}
    kernels_flag = "taichi" if device == "vulkan" else "both"
    for name in subjects:
        with tempfile.TemporaryDirectory() as tmp:
            js = Path(tmp) / "r.json"
            cmd = [sys.executable, "-m", "perf", name, "--quick", "--device", device, "--kernels", kernels_flag,
                   "--json", str(js)]
            t0 = time.perf_counter()
            print(f"[device-check] bench {name} on {device}", file=sys.stderr, flush=True)
            try:
                proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout, env=_env())
            except subprocess.TimeoutExpired:
                out[name] = {"error": f"timed out after {timeout:.0f} s"}
                continue
            entry = {"seconds": round(time.perf_counter() - t0, 1), "returncode": proc.returncode}
            if proc.returncode == 0 and js.exists():
                entry["result"] = json.loads(js.read_text())["subjects"].get(name)
            else:
                entry["error"] = (proc.stderr or proc.stdout)[-1500:]
            out[name] = entry
    return out


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def main(argv: list[str] | None = None, *, prog: str = "python -m perf device-check",
         parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser) -> int:
    from .__main__ import SUBJECTS

    p = parser_class(prog=prog, description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=["cuda", "vulkan", "cpu"], default="cuda")
    p.add_argument("--subjects", nargs="+", choices=sorted(SUBJECTS), default=sorted(SUBJECTS),
                   help="perf subjects to benchmark (default: all)")
    p.add_argument("--no-tests", action="store_true", help="skip the test-suite cases")
    p.add_argument("--no-bench", action="store_true", help="skip the benchmarks")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per pytest run / per subject")
    p.add_argument("--real-frames", type=int, default=60, help="frames of the shared Redwood sequence per pair "
                                                                "(0: skip the real runs)")
    p.add_argument("--out", help="JSON report (default: perf/results/device-check-<device>.json)")
    args = p.parse_args(argv)

    from swarmsplat import kernels
    from .common import machine_info, write_results

    out = Path(args.out or REPO / "perf" / "results" / f"device-check-{args.device}.json")
    report = {"device": args.device, "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "machine": machine_info(),
              "versions": versions(), "load_avg": list(os.getloadavg())}
    report["devices"] = [f"{b.name}-{b.device}" for b in kernels.devices()]
    report["devices_run"] = [f"{b.name}-{b.device}" for b in kernels.devices(run=True)]
    print(f"[device-check] working pairs: {', '.join(report['devices_run'])}", file=sys.stderr)
    if not any(d.endswith("-" + args.device) for d in report["devices_run"]):
        print(f"[device-check] warning: no backend works on {args.device!r} here; its cases will skip",
              file=sys.stderr)
    if not args.no_tests:
        print(f"[device-check] test cases for {args.device} ...", file=sys.stderr, flush=True)
        report["tests"] = run_tests(args.device, args.timeout)
        print(f"[device-check] tests: {report['tests'].get('counts', report['tests'].get('error'))}", file=sys.stderr)
    if not args.no_bench:
        report["bench"] = run_bench(args.device, args.subjects, args.timeout)
    if args.real_frames > 0:
        from .device_agreement import DATA, pairs_for, run_real

        if DATA.exists():
            report["real"] = run_real(DATA, args.real_frames, pairs_for(args.device), args.timeout)
            print(f"[device-check] real data agrees: {report['real']['agree']} {report['real']['reasons']}",
                  file=sys.stderr)
        else:
            report["real"] = {"skipped": f"{DATA} not present"}
    report["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    write_results(str(out), None, report)
    print(f"[device-check] wrote {out}", file=sys.stderr)
    failed = bool(report.get("tests", {}).get("failures")) or "error" in report.get("tests", {})
    failed = failed or any("error" in v for v in report.get("bench", {}).values())
    failed = failed or report.get("real", {}).get("agree") is False
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
