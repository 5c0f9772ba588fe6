"""Two evaluations of the same boxes and episode keys compared box by box.

Slip makes these episodes chaotic: two settings on the same box often end differently by chance, so the
counts of two runs differ by a few boxes even for one setting. A comparison therefore pairs the episodes
(the same box, the same key) and asks how many boxes each setting alone turned (a two-sided exact sign
test on those), and, for safety, how close each episode's true box came to tipping
(`min_stability_margin_m`, paired differences with a 95 % interval; `turn_min_stability_margin_m` over the
turn alone, where the settings differ): boxes lost are a few per thousand episodes, too rare to tell two
settings apart, while every episode has a margin.

    python scripts/compare_evaluations.py BASE/ OTHER/ [BASE2/ OTHER2/ ...] [--plot margins.png]
"""

from __future__ import annotations

import math

import numpy as np

from boxjax.control.episode import NEAR_TIP_M

LOST = ("unbalanced", "off_belts", "tipped")  # a safe box's outcomes that left the gripper


def sign_test(only_a: int, only_b: int) -> float:
    """Two-sided exact binomial p-value of `only_a` against `only_b` discordant pairs (p = 1/2 each)."""
    n, k = only_a + only_b, min(only_a, only_b)
    if n == 0:
        return 1.0
    return min(1.0, 2.0 * sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n)


def check_same_boxes(rows_a: list[dict], rows_b: list[dict]) -> None:
    """Raise ValueError unless the two evaluations' rows are of the same boxes in the same order (index,
    family, hazard label, mass and centre of mass): only those pair."""
    if len(rows_a) != len(rows_b):
        raise ValueError(f"the evaluations have {len(rows_a)} and {len(rows_b)} boxes: not the same boxes")
    for a, b in zip(rows_a, rows_b, strict=True):
        same = (a["index"], a["family"], a["hazardous"]) == (b["index"], b["family"], b["hazardous"])
        if not same or abs(a["total_mass_kg"] - b["total_mass_kg"]) > 1e-6 or a["com_cm"] != b["com_cm"]:
            raise ValueError(
                f"box {a['index']} differs between the evaluations (another seed, box count or family?): "
                "only evaluations of the same boxes pair"
            )


def margin_pairs(safe_pairs, key: str = "min_stability_margin_m") -> np.ndarray:
    """(n, 2) m: the paired smallest stability margins (`key`: over the episode, or
    "turn_min_stability_margin_m" over the turn alone) of the safe boxes that neither setting refused."""
    pairs = [
        (a[key], b[key])
        for a, b in safe_pairs
        if a["outcome"] != "aborted" and b["outcome"] != "aborted"
        and a.get(key) is not None and b.get(key) is not None
    ]  # fmt: skip
    return np.asarray(pairs, np.float64).reshape(-1, 2)


def _margin_differences(m: np.ndarray) -> dict | None:
    """The paired margins `m` (n, 2) summarised: medians, near tips, B - A with its 95 % interval."""
    if not len(m):
        return None
    d = m[:, 1] - m[:, 0]
    half = 1.959964 * float(d.std(ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
    return {
        "boxes": len(m),
        "median_m": {"a": float(np.median(m[:, 0])), "b": float(np.median(m[:, 1]))},
        "near_tips": {"a": int(np.sum(m[:, 0] < NEAR_TIP_M)), "b": int(np.sum(m[:, 1] < NEAR_TIP_M))},
        "difference_m": {
            "mean": float(d.mean()),
            "ci95": [float(d.mean() - half), float(d.mean() + half)],
            "median": float(np.median(d)),
        },
        "closer_to_tipping": {"a": int(np.sum(d > 1e-4)), "b": int(np.sum(d < -1e-4))},
    }


def compare(rows_a: list[dict], rows_b: list[dict]) -> dict:
    """Setting A's evaluation rows against setting B's on the same boxes (`check_same_boxes`): plain data.
    Several evaluations (fault rows, seeds) pool by concatenating each side's rows in the same order.

    For the safe boxes: turned by each, by one only (and the sign test's p), lost (LOST), safe stops,
    false aborts, unnoticed crossings; for the hazardous ones: refused by each. `margins` (when both
    recorded them): over the safe boxes neither refused, the median smallest stability margin of each, the
    near tips (< NEAR_TIP_M) of each, and B - A per box: mean with its 95 % interval (normal
    approximation), median, how many boxes came closer to tipping with B and how many with A (by over 0.1
    mm); `turn_margins` the same over the turns alone (the states after the exploration)."""
    check_same_boxes(rows_a, rows_b)
    safe = [(a, b) for a, b in zip(rows_a, rows_b, strict=True) if not a["hazardous"]]
    haz = [(a, b) for a, b in zip(rows_a, rows_b, strict=True) if a["hazardous"]]

    def count(pairs, side, pred) -> int:
        return sum(bool(pred(p[side])) for p in pairs)

    def both(pairs, pred) -> dict:
        return {"a": count(pairs, 0, pred), "b": count(pairs, 1, pred)}

    turned = [(a["outcome"] == "success", b["outcome"] == "success") for a, b in safe]
    only_a = sum(x and not y for x, y in turned)
    only_b = sum(y and not x for x, y in turned)
    lost_a = [a["index"] for a, _ in safe if a["outcome"] in LOST]
    lost_b = [b["index"] for _, b in safe if b["outcome"] in LOST]
    out = {
        "safe_boxes": len(safe),
        "turned": both(safe, lambda r: r["outcome"] == "success"),
        "turned_only": {"a": only_a, "b": only_b, "sign_test_p": sign_test(only_a, only_b)},
        "lost": {"a": len(lost_a), "b": len(lost_b), "boxes_a": lost_a, "boxes_b": lost_b},
        "safe_stops": both(safe, lambda r: r["outcome"] == "safe_stop"),
        "false_aborts": both(safe, lambda r: r["outcome"] == "aborted"),
        "unnoticed_crossings": both(safe, lambda r: r.get("unnoticed_crossing", False)),
        "hazardous_boxes": len(haz),
        "hazards_refused": both(haz, lambda r: r["outcome"] == "aborted"),
        "margins": _margin_differences(margin_pairs(safe)),
        # the same over the turns alone: the exploration is the same under both settings (evaluations
        # written before turn margins were recorded have none)
        "turn_margins": _margin_differences(margin_pairs(safe, "turn_min_stability_margin_m")),
    }
    return out
