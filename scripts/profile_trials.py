"""Where the trial kernel spends its time: ``perf`` samples of ``run_trials`` mapped to the
functions of warpis's compiled estimators module.

    python scripts/profile_trials.py [--scene occluded-quad] [--estimator independent:single:light-area]
                                     [--n 64] [--seconds 6] [--top 25]

Warp loads a CPU module through its own LLVM JIT, which ``perf`` cannot name: its samples
land on bare addresses.  This script runs ``run_trials`` in a loop in a child process (one
thread), records the child with ``perf record -p``, and maps each sampled address inside
the module to the function of the module's object file (in Warp's kernel cache) that
holds it: the child gives the address of the kernel's entry (Warp's ``wp_lookup`` of its
``…_cpu_forward`` symbol), the object's symbol table gives every function's offset,
static ones included (those LLVM kept out of line), and the module's code is one section.
Samples outside the module (Python, libc, the kernel) are listed by perf's own names.

Needs ``perf`` (Debian: ``linux-perf``; ``kernel.perf_event_paranoid`` ≤ 2 lets a user
profile their own processes) and binutils' ``nm``.  A development tool, not part of the
suite; it reads Warp internals (``warp._src.context``) that may move between releases.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = """
import sys, time
import warp as wp
import warp._src.context as context
import warpis
from warpis.kernels import engine, estimators
from warpis.kernels.precompiled import module_folders
scene_name, spec, n, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
scene = warpis.load_scene(scene_name)
engine.run_trials(scene, spec, n, 4, seed=0, threads=1)  # loads the module
kernel = estimators.trial_kernel
entry = kernel.get_mangled_name() + "_cpu_forward"
(exec_,) = [e for e in kernel.module.execs.values() if e is not None]
address = context.runtime.llvm.wp_lookup(exec_.handle.encode(), entry.encode())
folder = wp.config.kernel_cache_dir + "/" + module_folders()["warpis.kernels.estimators"]
print("READY", entry, hex(address), folder, flush=True)
sys.stdin.readline()  # the parent's perf is attached
start = time.perf_counter()
while time.perf_counter() - start < seconds:
    engine.run_trials(scene, spec, n, 2000, seed=1, threads=1)
"""

SAMPLE = re.compile(r"^\s+([\d.]+)%\s+\[.\]\s+(\S+)")


def functions(obj: Path) -> list[tuple[int, str]]:
    """(offset, demangled name) of every function of the object file, by offset."""
    out = subprocess.run(["nm", "-n", "-C", "--defined-only", str(obj)], capture_output=True, text=True,
                         check=True).stdout
    found = []
    for line in out.splitlines():
        parts = line.split(None, 2)
        if len(parts) == 3 and parts[1] in "tT":
            found.append((int(parts[0], 16), parts[2]))
    return found


def profile(args: argparse.Namespace) -> list[tuple[float, str]]:
    child = subprocess.Popen([sys.executable, "-c", CHILD, args.scene, args.estimator, str(args.n),
                              str(args.seconds + 2)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline().split()
        if not line or line[0] != "READY":
            sys.exit("the child did not start (run it by hand to see why)")
        _, entry, address, folder = line
        (obj,) = Path(folder).glob("*.o")
        with tempfile.TemporaryDirectory() as tmp:
            data = Path(tmp) / "perf.data"
            recorder = subprocess.Popen(["perf", "record", "-q", "-F", "4999", "-p", str(child.pid), "-o", str(data),
                                         "--", "sleep", str(args.seconds)], stderr=subprocess.DEVNULL)
            child.stdin.write("go\n")
            child.stdin.flush()
            recorder.wait()
            report = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort", "symbol",
                                     "--stdio"], capture_output=True, text=True, check=True).stdout
    finally:
        child.kill()
        child.wait()
    table = functions(obj)
    offsets = [offset for offset, _ in table]
    base = int(address, 16) - dict((name, offset) for offset, name in table)[entry]
    end = max(offsets) + (1 << 20)
    shares: collections.Counter[str] = collections.Counter()
    for line in report.splitlines():
        m = SAMPLE.match(line)
        if not m:
            continue
        share, symbol = float(m.group(1)), m.group(2)
        offset = int(symbol, 16) - base if symbol.startswith("0x") else -1
        if 0 <= offset < end:
            name = table[bisect.bisect_right(offsets, offset) - 1][1]
            shares["module: " + name.split("(")[0]] += share
        else:
            shares[symbol] += share
    return [(share, name) for name, share in shares.most_common()]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="occluded-quad")
    parser.add_argument("--estimator", default="independent:single:light-area")
    parser.add_argument("--n", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=6.0, help="how long perf records (default 6)")
    parser.add_argument("--top", type=int, default=25, help="rows to print (default 25)")
    args = parser.parse_args()
    missing = [tool for tool in ("perf", "nm") if shutil.which(tool) is None]
    if missing:
        sys.exit(f"profile_trials: needs {' and '.join(missing)} (Debian: linux-perf, binutils)")
    rows = profile(args)
    print(f"{args.estimator} on {args.scene}, N = {args.n}, one thread: share of perf's samples "
          "(\"module:\" = a function of the compiled estimators module)")
    for share, name in rows[:args.top]:
        print(f"{share:6.2f}%  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
