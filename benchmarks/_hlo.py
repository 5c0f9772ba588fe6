"""How many device operations a compiled program runs, counted from its optimised HLO (a GPU's cost proxy).

On a GPU every top-level operation of a compiled XLA program (a fusion, a custom call, a copy, a sort, ...)
is at least one kernel launch, and every iteration of a `while` loop also reads its condition back to the
host. A program whose work is a long chain of small operations inside loops is bound by these, not by
arithmetic. `dynamic_ops(compiled)` walks the HLO text of a compiled program: the operations of the entry
computation, plus, for each `while`, its trip count (XLA's `known_trip_count`) times the operations of its
body and condition, recursively; `call` and `conditional` count their callees (a conditional its largest
branch). Fused computations are not entered: a fusion is one operation. Bookkeeping that moves no data
(parameters, constants, tuples, get-tuple-element, bitcasts) is not counted.

The counts come from the compiling backend's HLO: on a CPU they are a proxy for a GPU's (the GPU compiler
fuses differently), good for comparing two programs' structure on the same backend, not for predicting a
GPU's milliseconds.
"""

from __future__ import annotations

import re

_FREE = {"parameter", "constant", "tuple", "get-tuple-element", "bitcast", "after-all", "partition-id"}
_HEADER = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s*\(.*\)\s*->\s*.*\{\s*$")
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*.*?\s([a-z][a-z0-9\-]*)\(")
_TRIP = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')


def _computations(text: str) -> tuple[dict[str, list[str]], str]:
    comps, entry, name = {}, None, None
    for line in text.splitlines():
        m = _HEADER.match(line)
        if m:
            name = m.group(1)
            comps[name] = []
            if line.startswith("ENTRY"):
                entry = name
        elif line.startswith("}"):
            name = None
        elif name is not None and "=" in line:
            comps[name].append(line)
    if entry is None:
        raise ValueError("no ENTRY computation in the HLO text")
    return comps, entry


def dynamic_ops(hlo_text: str) -> dict:
    """{'ops': operations run per call, 'while_iterations': loop iterations per call (each a condition read
    back on a GPU), 'static_ops': operations in the program text} of a compiled program's HLO text."""
    comps, entry = _computations(hlo_text)
    memo: dict[str, tuple[int, int]] = {}

    def attr(line, key):
        m = re.search(key + r"=%?([\w.\-]+)", line)
        return m.group(1) if m else None

    def walk(name: str) -> tuple[int, int]:
        if name in memo:
            return memo[name]
        ops = iters = 0
        for line in comps[name]:
            m = _INSTR.match(line)
            if not m or m.group(1) in _FREE:
                continue
            op = m.group(1)
            if op == "while":
                trip = _TRIP.search(line)
                n = int(trip.group(1)) if trip else 1
                b_ops, b_it = walk(attr(line, "body"))
                c_ops, c_it = walk(attr(line, "condition"))
                ops += n * (b_ops + c_ops)
                iters += n * (1 + b_it + c_it)
            elif op == "call":
                c_ops, c_it = walk(attr(line, "to_apply"))
                ops, iters = ops + c_ops, iters + c_it
            elif op == "conditional":
                branches = re.search(r"branch_computations=\{([^}]*)\}", line)
                names = [b.strip().lstrip("%") for b in branches.group(1).split(",")] if branches else []
                names += [n for n in (attr(line, "true_computation"), attr(line, "false_computation")) if n]
                walked = [walk(b) for b in names] or [(0, 0)]
                ops += 1 + max(w[0] for w in walked)
                iters += max(w[1] for w in walked)
            else:
                ops += 1
        memo[name] = (ops, iters)
        return memo[name]

    ops, iters = walk(entry)
    static = sum(
        1 for lines in comps.values() for ln in lines if (m := _INSTR.match(ln)) and m.group(1) not in _FREE
    )
    return {"ops": ops, "while_iterations": iters, "static_ops": static}
