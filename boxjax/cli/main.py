"""The `boxjax` command line (entry point `boxjax.cli:main`).

    boxjax simulate [--distribution D | --box FILE] --policy naive|random --steps 300 [--backend native|mjx]
    boxjax rotate [--distribution C | --box FILE] --estimator oracle|learned [--planner sampling|paper]
        [--seed S] [--plot f.png] [--animate f.gif] [--json]
    boxjax demo [--distribution A|B|C|D|uniform | --box FILE] [--plot boxjax_demo.png] [--animate f.gif]
    boxjax evaluate [--boxes 100] [--hazardous 30] [--box FILE] [--out DIR] [--plot f.png] [--json]
    boxjax box --random SEED --out FILE.npz | boxjax box FILE [--plot f.png]     (your own boxes)
    boxjax config [--out FILE.toml]                                              (the defaults as TOML)
    boxjax train-estimator [--boxes 2000] [--seed S] --out DIR [--backend native|mjx] [--chunk 500]
    boxjax train-moments [--boxes 2000] [--seed S] --out FILE.npz [--backend native|mjx] [--chunk 500]
    boxjax estimator-eval [--boxes 500] [--seed S] [--weights FILE]
    boxjax calibrate [--transitions 400] [--seed S] --out FILE [--plot FILE.png]
    boxjax train-baseline [--model blackbox|pets] [--distribution A] [--episodes 200] [--seed 0] --out DIR
        [--data FILE] [--epochs N] [--members K]
    boxjax rotate ... --model blackbox [--model-weights FILE] [--adapt-every 20] [--adapt-epochs 1]
    boxjax compare [--seeds 5] [--boxes A B C D] [--methods prior blackbox] [--out DIR]
    boxjax reproduce --out DIR [--quick] [--retrain] [--force] [--json]        (the paper's tables, figures)
    boxjax fault-table [--boxes 100] [--seed 0] [--rows ...] [--out FILE.json] [--plot FILE.png]
    boxjax rotate|evaluate ... [--obs-noise-mm 3] [--obs-latency 2] [--friction 0.4] [--monitor on|off]

Every command but `reproduce` (the shipped weights are the default gripper's) takes --config FILE.toml
(box, gripper and task parameters). With --json the last line printed is one JSON object (the summary);
everything else goes before it. Bad input, and an option that the chosen planner, model or estimator
does not use (`boxjax.cli.args`), exit with status 2 and one line saying what is wrong.

The commands that compile JAX programs keep them on disk between runs (`run_info.use_compilation_cache`:
~/.cache/boxjax/jax, or the folder in BOXJAX_COMPILATION_CACHE, "off" to disable), so a second
`evaluate` or `rotate` skips the planners' compilation.
"""

from __future__ import annotations

import argparse
import sys

from boxjax.cli import args as cli_args
from boxjax.cli import box as cli_box
from boxjax.cli import episodes as cli_episodes
from boxjax.cli import faults as cli_faults
from boxjax.cli import reproduce as cli_reproduce
from boxjax.cli import train as cli_train
from boxjax.cli.args import emit

# Commands that do not turn the compilation cache on here: nothing worth keeping to compile (box,
# config), or it does so itself after its own checks (reproduce: a refused DIR costs no JAX start-up).
_NO_COMPILATION = frozenset({"box", "config", "reproduce"})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="boxjax", description="Safe box rotation on a two-belt gripper.")
    sub = p.add_subparsers(dest="command", required=True)
    cli_episodes.add_parsers(sub)
    cli_box.add_parsers(sub)
    cli_train.add_parsers(sub)
    cli_reproduce.add_parsers(sub)
    cli_faults.add_parsers(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cli_args.resolve(args)
        if args.command not in _NO_COMPILATION:
            from boxjax import run_info

            run_info.use_compilation_cache()
        summary = args.func(args)
    except (ValueError, FileNotFoundError) as e:  # bad input (incl. CheckpointError): say what, no traceback
        sys.stderr.write(f"boxjax {args.command}: error: {e}\n")
        return 2
    if summary is not None and (args.command != "demo" or args.json):
        emit(summary, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
