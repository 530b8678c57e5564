"""Which vector loops of the built field kernels move vector registers to and from the stack.

    python -m benchmarks.profile_registers [--all]

A register tile (the MLP layers, their weight gradients) keeps its accumulators in vector registers; when
the compiler places the accumulator array in memory instead, every fused multiply-add of the inner loop
pays a store and a load (~1.5x the tile's time on the AVX2 tiles before DUALNERF_UNROLL). This reads the
loaded extension with `objdump -d` (binutils), finds its loops (backward jumps) with at least 8 fused
multiply-adds, and prints each with its count of vector moves through %rsp/%rbp. A tile loop should show
0; a few moves per loop that reload a mask or a constant are cheap (L1). The AVX-512 code is compiled in
on every x86-64 build (a target attribute), so this also checks it on a CPU that cannot run it.
--all: every such loop, not only those with stack moves. No timing: the numbers do not depend on load.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys

MIN_FMAS = 8
_FUNCTION = re.compile(r"^([0-9a-f]+) <(.*)>:$")
_INSTRUCTION = re.compile(r"^\s+([0-9a-f]+):\s+(.*)$")
_BACKWARD_JUMP = re.compile(r"\bj\w+\s+([0-9a-f]+) <")
_STACK = re.compile(r"\(%r[sb]p\)")


def vector_loops(disassembly: str):
    """(function, instructions, fused multiply-adds, vector stack moves) per loop with >= MIN_FMAS."""
    functions: list[tuple[str, list[tuple[int, str]]]] = []
    for line in disassembly.splitlines():
        if m := _FUNCTION.match(line):
            functions.append((m.group(2), []))
        elif (m := _INSTRUCTION.match(line)) and functions:
            functions[-1][1].append((int(m.group(1), 16), m.group(2)))
    for name, body in functions:
        if name.endswith("@plt"):
            continue
        for address, text in body:
            jump = _BACKWARD_JUMP.search(text)
            if not jump or int(jump.group(1), 16) >= address:
                continue
            loop = [t for a, t in body if int(jump.group(1), 16) <= a <= address]
            fmas = sum("fmadd" in t or "fmsub" in t for t in loop)
            spills = sum(bool(_STACK.search(t)) and ("ymm" in t or "zmm" in t) for t in loop)
            if fmas >= MIN_FMAS:
                yield name, len(loop), fmas, spills


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.profile_registers")
    parser.add_argument("--all", action="store_true", help="every loop with fused multiply-adds")
    args = parser.parse_args([] if argv is None else argv)
    from dualnerf import kernels

    module = kernels.grid_kernel()
    if module is None or shutil.which("objdump") is None:
        print("no compiled kernels or no objdump (binutils): nothing to read")
        return
    text = subprocess.run(["objdump", "-d", "--no-show-raw-insn", "-C", module.__file__], check=True,
                          capture_output=True, text=True).stdout
    loops = list(vector_loops(text))
    print(f"{kernels.kernel_name()}: {len(loops)} loops with >= {MIN_FMAS} fused multiply-adds")
    print(f"{'instructions':>12s} {'FMAs':>5s} {'stack moves':>11s}  function")
    for name, size, fmas, spills in loops:
        if spills or args.all:
            print(f"{size:12d} {fmas:5d} {spills:11d}  {name[:110]}")
    tiles = [loop for loop in loops if "tile" in loop[0] and loop[3]]
    print(f"tile loops with vector stack moves: {len(tiles)}"
          + (" (the <8, 4> tiles: 128-wide layers, not the default FieldConfig)"
             if tiles and all("<8, 4>" in t[0] for t in tiles) else ""))


if __name__ == "__main__":
    main(sys.argv[1:])
