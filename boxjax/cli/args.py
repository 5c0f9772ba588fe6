"""Every `boxjax` option either acts or is refused: one mechanism for all commands.

An option is declared with `option(parser, "--flag", default=..., used_by=(...), check=...)`. Its argparse
default is None, so after parsing the CLI knows exactly which options the user gave; `resolve(args)` then
fills in the defaults, refuses (ValueError -> exit 2) a given option whose conditions do not hold, naming
who uses it ("--rule is an option of the paper planner (--planner paper); it does nothing with --planner
sampling"), and checks its value ("--samples must be >= 1, got -3").

A condition is a function args -> None (holds) or the rest of the refusal's sentence: `when(dest, *values)`
(the option is used only when another option has one of these values), `without(dest, why)` (not used
when another option is given), `needs(dest)` (used only when another option is given).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

Condition = Callable[[argparse.Namespace], "str | None"]


@dataclass(frozen=True)
class Option:
    flag: str
    dest: str
    default: Any
    used_by: tuple[Condition, ...] = ()
    check: tuple[Callable[[Any], bool], str] | None = None


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def when(dest: str, *values, owner: str | None = None) -> Condition:
    """Used only when option `dest` has one of `values` (after defaults are filled in); `owner` names
    who uses it in the refusal ("the paper planner")."""

    def cond(args):
        have = getattr(args, dest)
        if have in values:
            return None
        setting = f"{_flag(dest)} {' / '.join(str(v) for v in values)}"
        who = setting if owner is None else f"{owner} ({setting})"
        return f"is an option of {who}; it does nothing with {_flag(dest)} {have}"

    return cond


def without(dest: str, why: str) -> Condition:
    """Not used when option `dest` is given; `why` says what happens instead."""

    def cond(args):
        return None if getattr(args, dest) is None else f"does nothing with {_flag(dest)}: {why}"

    return cond


def needs(dest: str, what: str = "") -> Condition:
    """Used only together with option `dest`."""

    def cond(args):
        return None if getattr(args, dest) is not None else f"does nothing without {_flag(dest)}{what}"

    return cond


def _tip_watch_on(args) -> str | None:
    """--tip-uncertainty is the tipping watch's: refused with --tip-stop-cm 0 (no watch)."""
    return "does nothing with --tip-stop-cm 0 (no tipping watch)" if args.tip_stop_cm == 0 else None


def at_least(n) -> tuple[Callable[[Any], bool], str]:
    return (lambda v: v >= n), f">= {n}"


def option(
    parser: argparse.ArgumentParser,
    flag: str,
    *,
    default: Any = None,
    used_by: tuple[Condition, ...] = (),
    check: tuple[Callable[[Any], bool], str] | None = None,
    help: str | None = None,  # noqa: A002 (argparse's name)
    **kwargs,
) -> None:
    """Declare `flag` on `parser` (a sub-command's parser); the declarations travel in its namespace."""
    dest = kwargs.pop("dest", flag.lstrip("-").replace("-", "_"))
    if help is not None and default is not None and default is not False:
        help = f"{help} (default {default})"
    parser.add_argument(flag, dest=dest, default=None, help=help, **kwargs)
    declared = parser.get_default("_options")
    if declared is None:
        declared = []
        parser.set_defaults(_options=declared)
    declared.append(Option(flag, dest, default, tuple(used_by), check))


def given(args: argparse.Namespace) -> set[str]:
    """The dests of the options the user gave (after `resolve`)."""
    return getattr(args, "_given", set())


def resolve(args: argparse.Namespace) -> argparse.Namespace:
    """Fill in defaults, then refuse unused options and bad values (ValueError naming the option)."""
    opts = getattr(args, "_options", None) or []
    args._given = {o.dest for o in opts if getattr(args, o.dest) is not None}
    for o in opts:
        if o.dest not in args._given:
            setattr(args, o.dest, o.default)
    for o in opts:
        if o.dest not in args._given:
            continue
        for cond in o.used_by:
            why = cond(args)
            if why is not None:
                raise ValueError(f"{o.flag} {why}")
        value = getattr(args, o.dest)
        if o.check is not None and not o.check[0](value):
            raise ValueError(f"{o.flag} must be {o.check[1]}, got {value}")
    return args


def emit(summary: dict, as_json: bool) -> None:
    """The summary: one JSON line (--json), or one `key: value` line per field."""
    import json

    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        for k, v in summary.items():
            sys.stdout.write(f"  {k:>22}: {v}\n")
    sys.stdout.flush()


# ----------------------------------------------------------------------------------------------------------
# Options several commands share.


def config_option(p: argparse.ArgumentParser, *used_by: Condition) -> None:
    option(
        p,
        "--config",
        metavar="FILE.toml",
        used_by=used_by,
        help="box, gripper and task parameters from a TOML file (`boxjax config` prints the defaults)",
    )


def exploration_option(p: argparse.ArgumentParser, *used_by: Condition) -> None:
    """--exploration fixed|designed|gentle: the 45-step exploration (`TaskConfig.exploration`; beats
    --config)."""
    from boxjax.config import EXPLORATIONS

    option(
        p,
        "--exploration",
        choices=EXPLORATIONS,
        used_by=used_by,
        help="the exploration sequence: the fixed one (the paper's shape, the default), the one designed "
        "for information (boxjax.estimator.design), or gentle (the fixed one with its first turn at half "
        "speed, for a late, noisy sensor); a learned estimator must be trained on it "
        "(train-estimator --exploration NAME)",
    )


def box_options(p: argparse.ArgumentParser, default: str | None, *used_by: Condition) -> None:
    """--distribution NAME or --box FILE: the box of one episode."""
    from boxjax.massdist import NAMES

    option(
        p,
        "--distribution",
        default=default,
        choices=NAMES,
        used_by=(without("box", "the box comes from the file"), *used_by),
        help="a named box",
    )
    option(
        p,
        "--box",
        metavar="FILE",
        used_by=used_by,
        help="your own box: .npz (occupancy, total_mass) or .json mixture spec (`boxjax box --help`)",
    )


def output_options(p: argparse.ArgumentParser, plot_help: str, animate: bool = True) -> None:
    option(p, "--plot", metavar="FILE.png", help=plot_help)
    if animate:
        option(
            p,
            "--animate",
            metavar="FILE.gif",
            help="write a top-view animation of the episode (belts, box, centre of mass, corridor)",
        )
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")


def steps_or_off(text: str) -> int | None:
    """--slow-when-late: a whole number of control steps >= 0, or "off" (None)."""
    if text.strip().lower() == "off":
        return None
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of control steps or 'off', got {text!r}"
        ) from None
    if value < 0:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of control steps >= 0 or 'off', got {value}"
        )
    return value


def guard_value(text: str) -> float:
    """--explore-guard: a fraction of the balance limit in (0, 1), or "off" (0.0, which the controller
    config reads as None)."""
    if text.strip().lower() == "off":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a fraction of the balance limit or 'off', got {text!r}"
        ) from None
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(
            f"expected a fraction of the balance limit in (0, 1) or 'off', got {text!r}"
        )
    return value


def planner_options(
    p: argparse.ArgumentParser,
    *used_by: Condition,
    calibration: bool = True,
    prior: tuple[Condition, ...] = (),
) -> None:
    """--planner and the options that belong to one planner each (refused with another); --variant of the
    physics prior (with the extra conditions `prior`), and --calibration (the paper prior's force map)
    where the command can pass one to the controller."""
    from boxjax.planners.paper import RULES
    from boxjax.planners.registry import PLANNERS

    option(
        p,
        "--planner",
        default="sampling",
        choices=PLANNERS,
        used_by=used_by,
        help="paper: one-step Pareto random shooting (§2.3); sampling: predictive sampling over sequences; "
        "simulator: privileged reference that plans with MuJoCo itself (oracle estimator only, slow)",
    )
    paper = when("planner", "paper", owner="the paper planner")
    option(p, "--rule", default="random", choices=RULES, used_by=(*used_by, paper), help="Pareto-front rule")
    option(
        p,
        "--samples",
        type=int,
        used_by=(*used_by, when("planner", "paper", "sampling", owner="the paper and sampling planners")),
        check=at_least(1),
        help="actions scored per control step (paper planner, default 50) or rollouts per control step "
        "(sampling planner, default 64; on an accelerator try 1024 with --gradient-steps 0)",
    )
    option(
        p,
        "--horizon",
        type=int,
        default=1,
        used_by=(*used_by, paper),
        check=at_least(1),
        help="prediction steps per candidate",
    )
    option(
        p,
        "--gradient-steps",
        type=int,
        used_by=(*used_by, when("planner", "sampling", owner="the sampling planner")),
        check=at_least(0),
        help="Adam steps through the prior on the chosen sequence (default 5; 0: none)",
    )
    option(
        p,
        "--friction-set",
        type=float,
        nargs="+",
        metavar="MU",
        used_by=(*used_by, *prior, when("planner", "sampling", owner="the sampling planner")),
        check=(
            (lambda v: len(v) >= 2 and all(0 < m < 5 for m in v)),
            "two or more friction coefficients in (0, 5)",
        ),
        help="robust planning: plan over these belt friction coefficients, one physics prior each, every "
        "candidate scored by its mean cost over them (e.g. 0.35 0.5 0.65; ~3x the planning time)",
    )
    option(
        p,
        "--explore-guard",
        type=guard_value,
        default=0.875,
        metavar="F|off",
        used_by=used_by,
        help="a box whose balance error passes this fraction of the balance limit during the fixed "
        "exploration is stopped (--guard-stop) and refused, not lost; off: the paper's fixed exploration",
    )
    option(
        p,
        "--guard-lead",
        type=int,
        default=3,
        check=at_least(0),
        used_by=(*used_by, lambda a: None if a.explore_guard else "does nothing with --explore-guard off"),
        help="control steps the exploration guard looks ahead along the balance error's trend (0: the "
        "present error alone)",
    )
    option(
        p,
        "--guard-stop",
        default="auto",
        choices=("auto", "recentre", "hold"),
        used_by=(*used_by, lambda a: None if a.explore_guard else "does nothing with --explore-guard off"),
        help="what the exploration guard does once tripped: recentre the carriages under the box, hold "
        "them still (the belts stop either way), or auto: hold when the sensor's pose is noisy or late, "
        "re-centre when it is exact",
    )
    option(
        p,
        "--variant",
        default="slip",
        choices=("slip", "paper"),
        used_by=(*used_by, *prior),
        help="physics prior: slip (friction on the belt-box slip) or paper (calibrated force map, eqs. 4-14)",
    )
    if not calibration:
        return
    option(
        p,
        "--calibration",
        metavar="FILE.npz",
        used_by=(*used_by, *prior, when("variant", "paper")),
        help="action -> force map of `boxjax calibrate` for the paper prior (default: the shipped one)",
    )


def fault_options(p: argparse.ArgumentParser, *used_by: Condition) -> None:
    """How the simulated world differs from the controller's (`boxjax.sim.faults.Faults`; a [faults]
    table of --config sets them too, these override it), and --monitor."""
    nonneg = ((lambda v: v >= 0), ">= 0")
    for flag, kind, help_ in (
        ("--obs-noise-mm", float, "std of gaussian noise on the observed box position (mm)"),
        ("--obs-noise-deg", float, "std of gaussian noise on the observed box yaw (degrees)"),
        ("--obs-latency", int, "control steps between the world and the observation (0.05 s each)"),
        ("--drop-rate", float, "probability that a camera frame is lost (the last one is held), in [0, 1)"),
        ("--action-latency", int, "control steps between an action sent and applied"),
        ("--friction", float, "the simulator's box-belt friction (the model keeps the config's)"),
        ("--mass-shift-kg", float, "mass that slides 10 cm inside the box at a random step (kg)"),
    ):
        option(p, flag, type=kind, metavar="X", used_by=used_by, check=nonneg, help=help_)
    option(
        p,
        "--friction-belt",
        choices=("both", "1", "2"),
        used_by=(*used_by, needs("friction")),
        help="which belt has --friction (default both)",
    )
    option(
        p,
        "--monitor",
        default="on",
        choices=("on", "off"),
        used_by=used_by,
        help="the runtime safety monitor between the planner and the gripper (off: the paper's controller)",
    )
    option(
        p,
        "--tip-stop-cm",
        type=float,
        default=0.8,
        metavar="X",
        check=((lambda v: 0 <= v < 15), "in [0, 15)"),
        used_by=(*used_by, when("monitor", "on", owner="the runtime safety monitor")),
        help="the monitor stops an action whose predicted stability margin (how far the centre of mass stays "
        "inside the belts' support) falls under this many cm; 0: no tipping watch",
    )
    option(
        p,
        "--tip-uncertainty",
        default="sigma",
        choices=("y", "pose", "sigma"),
        used_by=(*used_by, when("monitor", "on", owner="the runtime safety monitor"), _tip_watch_on),
        help="what the tipping watch counts for the pose it cannot see: y: the balance check's margin "
        "subtracted, 1:1; pose: that margin and the yaw's over the delay, each times how fast the stability "
        "margin falls with the pose there; sigma: the margin itself at poses that far off (axes and "
        "diagonals)",
    )
    option(
        p,
        "--slow-when-late",
        type=steps_or_off,
        default=2,
        metavar="N|off",
        used_by=(*used_by, when("planner", "sampling", owner="the sampling planner")),
        help="past this many control steps of delay (sensor latency + action latency) the sampling planner's "
        "belt-speed and carriage-step caps shrink by (1 + N) / (1 + delay); off: never",
    )
