"""The report of `boxjax reproduce`: results (plain data, `boxjax.experiments.reproduce.run`) in, markdown
out.

Pure: `render(results)` reads nothing and writes nothing; figures are the relative paths in the results,
linked as images. Every table puts the paper's own numbers beside ours.
"""

from __future__ import annotations

from boxjax.experiments.data_efficiency import format_table

PAPER_TITLE = (
    "Salehi & Doncieux, *Data-efficient, Explainable and Safe Box Manipulation: Illustrating the Advantages "
    "of Physical Priors in Model-Predictive Control* (L4DC 2024)"
)
METHOD_NAMES = {"prior": "physical priors (learned H)", "blackbox": "black box W (baseline)"}


def _f(x, fmt: str = "{:.1f}", none: str = "-") -> str:
    return none if x is None else fmt.format(x)


def _table(header, rows) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return lines + [""]


def _paper_success(x) -> str:
    if x is None:
        return "-"
    return x if isinstance(x, str) else f"{100 * x:.0f} %"


def _outcomes(counts: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items()) or "-"


def _header(r: dict) -> list[str]:
    m, v = r["machine"], r["versions"]
    mode = "quick" if r["mode"]["quick"] else "full"
    weights = "retrained by this run (--retrain)" if r["mode"]["retrain"] else "shipped (boxjax/data)"
    load = m["load_average"]
    load_end = m.get("load_average_end")

    def la(x):
        return "-" if x is None else " / ".join(f"{y:.2f}" for y in x)

    commit = v["git_commit"] or "not a git checkout"
    if v["git_commit"] and v["git_dirty"]:
        commit += " (with uncommitted changes)"
    lines = [
        "# boxjax reproduce: the paper's experiments",
        "",
        f"Reproducing {PAPER_TITLE} in boxjax's MuJoCo simulation (the paper used pybullet).",
        "",
        f"Command: `{r['command']}`  ",
        f"Started {r['started_utc']}; mode: {mode}; weights: {weights}; total wall time "
        f"{r['wall_s']['total']:.1f} s.",
        "",
        "## Machine, versions, seeds",
        "",
    ]
    lines += _table(
        ("item", "value"),
        [
            ("CPU", m["cpu"]),
            ("cores", m["cores"]),
            ("load average at start (1 / 5 / 15 min)", la(load)),
            ("load average at end (1 / 5 / 15 min)", la(load_end)),
            ("JAX devices", ", ".join(m["jax_devices"])),
            ("platform", m["platform"]),
            ("python", v["python"]),
            ("jax / jaxlib", f"{v['jax']} / {v['jaxlib']}"),
            ("mujoco", v["mujoco"]),
            ("numpy", v["numpy"]),
            ("boxjax", v["boxjax"]),
            ("boxjax git commit", commit),
            *((f"seeds: {k}", s) for k, s in r["seeds"].items()),
        ],
    )
    lines += ["### Wall time per part", ""]
    lines += _table(("part", "wall s"), [(k, f"{s:.1f}") for k, s in r["wall_s"].items()])
    t1 = r["table1"]["wall_s"]
    lines += [
        f"Table 1 splits into the prior's episodes {t1['prior']:.1f} s (batched: "
        f"{r['table1']['prior_batched']}) and W's {t1['blackbox']:.1f} s (batched: "
        f"{r['table1'].get('blackbox_batched', False)}; on a CPU a batch of W's episodes is no faster: "
        "its planning is bound by W's matrix products).",
        "",
    ]
    if r["reductions"]:
        lines += ["### What this run does less than the paper", ""]
        lines += [f"* {x}" for x in r["reductions"]] + [""]
    if r.get("retrain"):
        rt = r["retrain"]
        lines += ["### Retrained weights (--retrain)", ""]
        lines += _table(
            ("model", "made from", "file", "wall s"),
            [
                (
                    "calibration",
                    f"{rt['calibration']['transitions']} transitions, seed {rt['seed']}",
                    f"`{rt['calibration']['file']}`",
                    f"{rt['calibration']['wall_s']:.1f}",
                ),
                (
                    "H",
                    f"{rt['estimator']['boxes']} boxes ({rt['estimator']['transitions']} transitions), "
                    f"validation IoU {_f(rt['estimator']['validation']['iou_median'], '{:.3f}')}",
                    f"`{rt['estimator']['file']}`",
                    f"{rt['estimator']['wall_s']:.1f}",
                ),
                (
                    "W",
                    f"{rt['baseline']['episodes']} episodes of A ({rt['baseline']['transitions']} "
                    "transitions)",
                    f"`{rt['baseline']['file']}`",
                    f"{rt['baseline']['wall_s']:.1f}",
                ),
            ],
        )
    return lines


def _table1(t: dict) -> list[str]:
    lines = [
        "## Table 1: physical priors vs the black-box baseline W",
        "",
        "`comparison.compare`: the same predictive-sampling MPC; the prior with the learned H (45-step "
        "exploration, counted in its steps, then refuse or turn; zero-shot), W with no exploration, adapted "
        f"online for {t['adapt_epochs']} epoch every {t['adapt_every']} steps on the episode's data (as the "
        f"paper). Seeds {', '.join(map(str, t['seeds']))}; episode key {t['episode_key']}. Steps: the mean "
        "over successful episodes. The prior's wall time per episode is the batch's divided by its episodes.",
        "",
    ]
    rows = []
    for r in t["table"]:
        n_ok = round(r["success_ratio"] * r["episodes"])
        bal = None if r["worst_balance_m"] is None else 100 * r["worst_balance_m"]
        rows.append(
            (
                r["box"],
                METHOD_NAMES.get(r["method"], r["method"]),
                f"{n_ok}/{r['episodes']}",
                f"{100 * r['success_ratio']:.0f} %",
                r["refused"],
                _outcomes(r["outcomes"]),
                _f(r["mean_steps_successes"]),
                _f(bal, "{:.2f} cm"),
                _f(r["mean_wall_s"]),
                _f(r["mean_adapt_s"], "{:.2f}"),
                _paper_success(r["paper_success"]),
                _f(r["paper_steps"]),
            )
        )
    lines += _table(
        (
            "box",
            "method",
            "success",
            "success ratio",
            "refused",
            "outcomes",
            "steps",
            "worst balance",
            "wall s / episode",
            "adaptation s / episode",
            "paper success",
            "paper steps",
        ),
        rows,
    )
    lines += ["Every episode:", ""]
    lines += _table(
        ("box", "method", "seed", "outcome", "steps", "worst balance", "wall s"),
        [
            (
                r["box"],
                r["method"],
                r["seed"],
                r["outcome"],
                r["steps"],
                f"{100 * r['max_balance_error_m']:.2f} cm",
                f"{r['wall_s']:.1f}",
            )
            for r in t["rows"]
        ],
    )
    return lines


def _table2(t: dict) -> list[str]:
    lines = [
        "## Table 2: the data each model was trained on",
        "",
        "`comparison.table2`, read from the weight files.",
        "",
    ]
    lines += _table(
        ("model", "transitions", "data from", "zero-shot", "paper"),
        [
            (
                r["model"],
                r["transitions"],
                r["data_from"],
                "yes" if r["zero_shot"] else "no (adapted online)",
                r["paper"] or "-",
            )
            for r in t["rows"]
        ],
    )
    return lines


def _rate(n_ok, n) -> str:
    return f"{n_ok}/{n}"


def _validation(v: dict) -> list[str]:
    s, first, paper = v["summary"], v["first"], v["paper"]
    k = first["safe_boxes"]

    def ci(x):
        return "-" if x is None else f"{100 * x[0]:.1f}-{100 * x[1]:.1f} %"

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f} %"

    lines = [
        "## §4.3: random boxes (learned H)",
        "",
        "`experiments.evaluate`: one closed-loop episode per box, batched, boxes and episode keys from seed "
        f"{v['seed']} (`experiments.make_boxes`). The paper's experiment (30 random safe boxes) is the first "
        f"{k} safe boxes of the same run: the safe boxes are drawn in sequence from their own key and box "
        "j's episode key is fold_in(key, j), safe boxes first, so they are the boxes and keys of `boxjax "
        f"evaluate --boxes {k} --seed {v['seed']}` (the batched planner's round-off depends on the call's "
        "width, so a separate run may end an episode differently).",
        "",
    ]
    hz = s["hazardous_boxes"]

    def row(label, x, hazards, paper_cell):
        return (
            label,
            _rate(x["safe_success"], x["safe_boxes"]),
            pct(x["safe_success_rate"]),
            ci(x["safe_success_ci95"]),
            x["false_aborts"],
            _outcomes(x["failures"]),
            hazards,
            paper_cell,
        )

    paper_cell = f"{paper['safe_success']}/{paper['safe_boxes']} = {100 * paper['safe_success_rate']:.1f} %"
    rows = [
        row(f"first {k} safe boxes (the paper's experiment)", first, "-", paper_cell),
        row(
            f"{s['safe_boxes']} safe + {hz} hazardous boxes",
            s,
            _rate(s["hazard_aborted"], hz) if hz else "-",
            "-",
        ),
    ]
    lines += _table(
        (
            "boxes",
            "safe turned",
            "rate",
            "95 % CI (Wilson)",
            "false aborts",
            "failures",
            "hazardous refused",
            "paper",
        ),
        rows,
    )
    st, bal = s["steps_success"], s["max_balance_error_m"]
    lines += [
        f"Steps of the turned boxes: median {_f(st['median'])}, max {_f(st['max'])}. Worst balance error per "
        f"episode: median {_f(None if bal['median'] is None else 100 * bal['median'], '{:.2f}')} cm, max "
        f"{_f(None if bal['max'] is None else 100 * bal['max'], '{:.2f}')} cm. Episode wall time "
        f"{s['wall_s']:.1f} s for all {s['safe_boxes'] + hz} boxes.",
        "",
        "### Fig. 3 (c): balance error over the validation boxes",
        "",
        f"![Fig. 3 (c)]({v['fig3c']})",
        "",
        "### Fig. 2 (c, d): true and predicted voxels of a random test box",
        "",
    ]
    f2 = v["fig2"]
    if f2 is None:
        lines += ["No safe validation box kept its exploration (all lost while exploring): no figure.", ""]
    else:
        lines += [
            f"Validation box {f2['box']} ({f2['true_mass_kg']:.2f} kg), H's prediction from its 45-step "
            f"exploration: IoU {f2['iou']:.3f}, mass error {f2['mass_error_kg']:+.3f} kg, centre-of-mass "
            f"error {f2['com_error_cm']:.2f} cm.",
            "",
            f"![Fig. 2 (c, d)]({f2['figure']})",
            "",
        ]
    return lines


def _force_map(fm: dict) -> list[str]:
    lines = [
        "## Fig. 3 (a, b): the action -> force map, all four forces",
        "",
        f"The calibration file `{fm['file']}` (made by `{fm['file_command']}`, {fm['file_transitions']} "
        "transitions): its mean and +-1 std per action value, and the samples of "
        f"{fm['samples_transitions']} transitions collected again with seed {fm['samples_seed']}; refit from "
        f"them, the means differ from the file's by at most {fm['refit_max_abs_mean_diff_N']:.3g} N. The "
        "default controller's `slip` prior does not use this map; the paper prior (`--variant paper`) does.",
        "",
    ]
    lines += _table(
        ("force", "mean range", "std range"),
        [
            (
                k,
                f"{x['mean_range_N'][0]:+.2f} .. {x['mean_range_N'][1]:+.2f} N",
                f"{x['std_range_N'][0]:.2f} .. {x['std_range_N'][1]:.2f} N",
            )
            for k, x in fm["forces"].items()
        ],
    )
    return lines + [f"![Fig. 3 (a, b)]({fm['figure']})", ""]


def _data_efficiency(d: dict) -> list[str]:
    lines = ["## Data efficiency", ""]
    if not d["measured"]:
        return lines + [
            f"Not measured: {d['reason']}. Run `{d['command']}` to measure the curve (it writes "
            f"`{d['source']}`), then run `boxjax reproduce` again.",
            "",
        ]
    curve = d["curve"]
    lines += [f"From `{d['source']}` (made by `{curve.get('command')}`).", ""]

    lines += [format_table(curve), ""]
    return lines + [f"![data efficiency]({d['figure']})", ""]


def render(results: dict) -> str:
    """The report (markdown) of `reproduce.run`'s results."""
    lines = _header(results)
    lines += _table1(results["table1"])
    lines += _table2(results["table2"])
    lines += _validation(results["validation"])
    lines += _force_map(results["force_map"])
    lines += _data_efficiency(results["data_efficiency"])
    return "\n".join(lines)
