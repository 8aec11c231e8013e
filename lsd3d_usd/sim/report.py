"""`sim report`: runs compared — mean scores with 95 % intervals over episodes, and a plot.

A run is a `sim run` output folder (episode_*/metrics.json). The interval is the mean's
Student-t 95 % confidence interval over the run's episodes (scipy.stats.t); a run of one
episode has none.
"""
from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import atomic_write_bytes

SCORES = ("rc", "driving_score", "pdms", "hd_score", "nc", "dac", "ddc", "ttc", "comfort", "ep")
MAX_METRICS_BYTES = 256 * 1024 * 1024


def read_run(folder) -> list[dict]:
    """The episodes' metrics.json of one run folder, in episode order."""
    p = Path(folder)
    if not p.is_dir():
        raise InputError(f"{folder}: no such folder (a `sim run` output)")
    files = sorted(p.glob("episode_*/metrics.json"))
    if not files:
        raise InputError(f"{folder}: no episode_*/metrics.json (a `sim run` output)")
    out = []
    for f in files:
        if not f.is_file() or f.stat().st_size > MAX_METRICS_BYTES:
            raise InputError(f"{f}: not a regular file under {MAX_METRICS_BYTES >> 20} MB")
        try:
            d = json.loads(f.read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"{f}: not valid JSON ({e})") from None
        if not isinstance(d, dict) or not isinstance(d.get("summary"), dict):
            raise InputError(f"{f}: no \"summary\" object (not a sim run's metrics.json)")
        out.append(d)
    return out


def mean_ci(values) -> tuple[float | None, float | None, int]:
    """(mean, half width of the 95 % interval, n) of the finite values."""
    from scipy import stats
    v = np.array([x for x in values if x is not None and math.isfinite(float(x))], np.float64)
    if not len(v):
        return None, None, 0
    if len(v) == 1:
        return float(v[0]), None, 1
    half = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    return float(v.mean()), half, len(v)


def _groups(folder, eps: list[dict]) -> list[tuple[str, list[dict]]]:
    """A run's rows: the whole run, or one per scenario when its episodes played scenarios
    ("RUN [name]", in first-episode order)."""
    if not any(isinstance(e.get("scenario"), dict) for e in eps):
        return [(str(folder), eps)]
    by: dict[str, list] = {}
    for e in eps:
        sc = e.get("scenario") if isinstance(e.get("scenario"), dict) else {}
        by.setdefault(str(sc.get("name", "-")), []).append(e)
    return [(f"{folder} [{name}]", group) for name, group in by.items()]


def compare(folders) -> dict:
    """{row: {score: {mean, ci95, n}, "episodes": n, "reasons": {...}, "policy": ...}}: a row
    per run, or per run and scenario (with "scenario_end": the share of its episodes whose
    stop trigger fired, "completed": whose storyboard completed)."""
    runs = {}
    for f in folders:
        for key, eps in _groups(f, read_run(f)):
            runs[key] = _row(eps)
    return runs


def _row(eps: list[dict]) -> dict:
    row = {"episodes": len(eps), "policy": sorted({str(e.get("policy")) for e in eps}),
           "reasons": {}}
    for e in eps:
        r = str(e.get("reason"))
        row["reasons"][r] = row["reasons"].get(r, 0) + 1
    for k in SCORES:
        m, h, n = mean_ci(e["summary"].get(k) for e in eps)
        row[k] = {"mean": m, "ci95": h, "n": n}
    m, h, n = mean_ci(float(e["summary"].get("at_fault_collisions", 0) > 0) for e in eps)
    row["collided"] = {"mean": m, "ci95": h, "n": n}
    scs = [e["scenario"] for e in eps if isinstance(e.get("scenario"), dict)]
    if scs:
        row["scenario"] = str(scs[0].get("name"))
        for k, field in (("scenario_end", "stop_trigger_fired"), ("completed", "storyboard_completed")):
            m, h, n = mean_ci(float(bool(s.get(field))) for s in scs)
            row[k] = {"mean": m, "ci95": h, "n": n}
    return row


def format_table(runs: dict) -> str:
    cols = ("rc", "driving_score", "pdms", "hd_score", "nc", "dac", "comfort", "collided")
    head = f"{'run':30s} {'n':>3s} " + " ".join(f"{c:>15s}" for c in cols)
    lines = [head]
    for run, row in runs.items():
        cells = []
        for c in cols:
            m, h = row[c]["mean"], row[c]["ci95"]
            cells.append(f"{'-':>15s}" if m is None else
                         f"{m:7.3f} ±{h:6.3f}" if h is not None else f"{m:7.3f}        ")
        name = run if len(run) <= 30 else "…" + run[-29:]
        lines.append(f"{name:30s} {row['episodes']:3d} " + " ".join(f"{c:>15s}" for c in cells))
        ended = ", ".join(f"{k} {v}" for k, v in sorted(row["reasons"].items()))
        if "scenario_end" in row:
            ended += (f"; stop trigger fired {row['scenario_end']['mean']:.2f}, "
                      f"storyboard completed {row['completed']['mean']:.2f}")
        lines.append(f"{'':30s}     ended: " + ended)
    return "\n".join(lines)


def plot(runs: dict, path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = ("rc", "driving_score", "pdms", "hd_score", "nc", "dac", "comfort")
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=110)
    w = 0.8 / max(1, len(runs))
    for i, (run, row) in enumerate(runs.items()):
        m = [row[c]["mean"] if row[c]["mean"] is not None else np.nan for c in cols]
        e = [row[c]["ci95"] or 0.0 for c in cols]
        ax.bar(np.arange(len(cols)) + i * w, m, w, yerr=e, capsize=3, label=Path(run).name or run)
    ax.set_xticks(np.arange(len(cols)) + w * (len(runs) - 1) / 2, cols)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("mean over episodes (95 % CI)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
