"""How many device operations a compiled program runs, counted from its optimised HLO (a GPU's cost proxy).

On a GPU every top-level operation of a compiled XLA program (a fusion, a custom call, a copy, a sort, ...)
is at least one kernel launch, and every iteration of a `while` loop also reads its condition back to the
host. A program whose work is a long chain of small operations inside loops is bound by these, not by
arithmetic. `dynamic_ops(compiled)` walks the HLO text of a compiled program: the operations of the entry
computation, plus, for each `while`, its trip count (XLA's `known_trip_count`) times the operations of its
body and condition, recursively; `call` and `conditional` count their callees (a conditional its largest
branch). Fused computations are not entered: a fusion is one operation. Bookkeeping that moves no data
(parameters, constants, tuples, get-tuple-element, bitcasts) is not counted.

`by_source(compiled_text, package)` splits the same count by where the operations come from: each
operation's innermost stack frame inside `package` (the module and function, from the HLO's stack-frame
table), so a profile says which functions a program's operations are spent in.

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
_FRAME = re.compile(r"stack_frame_id=(\d+)")


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
    ops, iters = _walk(comps, entry, lambda line, n: None)
    static = sum(
        1 for lines in comps.values() for ln in lines if (m := _INSTR.match(ln)) and m.group(1) not in _FREE
    )
    return {"ops": ops, "while_iterations": iters, "static_ops": static}


def by_source(hlo_text: str, package: str = "boxjax") -> dict[str, int]:
    """Operations run per call, by the innermost function of `package` they were traced from
    ("module.py:function"; "other" where no frame lies in the package), largest first."""
    comps, entry = _computations(hlo_text)
    frames = _frames(hlo_text)
    counts: dict[str, int] = {}

    def source(line: str) -> str:
        m = _FRAME.search(line)
        frame, seen = (int(m.group(1)) if m else None), set()
        while frame in frames and frame not in seen:
            seen.add(frame)
            path, function, parent = frames[frame]
            if f"/{package}/" in path:
                return f"{path.split(f'/{package}/', 1)[1]}:{function}"
            frame = parent
        return "other"

    def count(line: str, n: int) -> None:
        key = source(line)
        counts[key] = counts.get(key, 0) + n

    _walk(comps, entry, count)
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


def _frames(text: str) -> dict[int, tuple[str, str, int]]:
    """The HLO text's stack-frame table: frame id -> (file, function, parent frame id)."""
    section, files, functions, locations, frames = None, {}, {}, {}, {}
    for line in text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = line
            continue
        m = re.match(r"^(\d+) (.*)$", line)
        if not m:
            section = None if not line.strip() else section
            continue
        i, rest = int(m.group(1)), m.group(2)
        if section == "FileNames":
            files[i] = rest.strip('"')
        elif section == "FunctionNames":
            functions[i] = rest.strip('"')
        elif section == "FileLocations":
            f = re.search(r"file_name_id=(\d+) function_name_id=(\d+)", rest)
            locations[i] = (int(f.group(1)), int(f.group(2)))
        elif section == "StackFrames":
            f = re.search(r"file_location_id=(\d+) parent_frame_id=(\d+)", rest)
            frames[i] = (int(f.group(1)), int(f.group(2)))
    out = {}
    for i, (loc, parent) in frames.items():
        file_id, function_id = locations.get(loc, (None, None))
        out[i] = (files.get(file_id, ""), functions.get(function_id, ""), parent)
    return out


def _walk(comps: dict[str, list[str]], entry: str, visit) -> tuple[int, int]:
    """(operations, loop iterations) one run of `entry` executes; `visit(line, times)` is told each
    counted operation's line and how many times a run executes it."""

    def attr(line, key):
        m = re.search(key + r"=%?([\w.\-]+)", line)
        return m.group(1) if m else None

    def walk(name: str, times: int) -> tuple[int, int]:
        ops = iters = 0
        for line in comps[name]:
            m = _INSTR.match(line)
            if not m or m.group(1) in _FREE:
                continue
            op = m.group(1)
            if op == "while":
                trip = _TRIP.search(line)
                n = int(trip.group(1)) if trip else 1
                b_ops, b_it = walk(attr(line, "body"), times * n)
                c_ops, c_it = walk(attr(line, "condition"), times * n)
                ops += n * (b_ops + c_ops)
                iters += n * (1 + b_it + c_it)
            elif op == "call":
                c_ops, c_it = walk(attr(line, "to_apply"), times)
                ops, iters = ops + c_ops, iters + c_it
            elif op == "conditional":
                branches = re.search(r"branch_computations=\{([^}]*)\}", line)
                names = [b.strip().lstrip("%") for b in branches.group(1).split(",")] if branches else []
                names += [n for n in (attr(line, "true_computation"), attr(line, "false_computation")) if n]
                walked = [walk(b, 0) for b in names]  # which branch runs is data: count the largest
                visit(line, times)
                ops += 1
                if walked:
                    b_ops, b_it = walk(names[max(range(len(names)), key=lambda i: walked[i][0])], times)
                    ops, iters = ops + b_ops, iters + b_it
            else:
                visit(line, times)
                ops += 1
        return ops, iters

    return walk(entry, 1)
