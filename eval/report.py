"""Tables of evaluation results: per-episode CSV, aggregated Markdown with 95% confidence intervals."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from pathlib import Path

from av_gym.atomic import write_texts_atomic
from av_gym.metrics import aggregate, format_ci, kind_of, markdown_table

HEADLINE = {
    "left_turn": ["collision", "success", "time_to_exit_s", "min_ttc_s", "stopped", "mean_speed_mps",
                  "intervention", "interventions", "override_fraction", "return"],
    "lane_keeping": ["lap_completed", "cte_mean_abs_m", "cte_max_abs_m", "cte_mean_abs_units", "cte_std_units",
                     "cte_max_abs_units", "lane_departures", "steering_sign_changes_per_100m", "return"],
}


def summary_table(rows: list[dict], scenario: str) -> str:
    """Markdown table: one line per agent, each headline metric as ``mean [95% CI]``, the interval its declared
    kind calls for (av_gym/metrics/kinds.py)."""
    agg = aggregate(rows, group_key="agent")
    metrics = [m for m in HEADLINE[scenario] if m in rows[0]]
    table = []
    for g in agg:
        line = {"agent": g["agent"], "n": g["n"]}
        for m in metrics:
            line[m] = format_ci(g[m], g[m + "_lo"], g[m + "_hi"], kind_of(m) == "rate")
        table.append(line)
    return markdown_table(table, ["agent", "n", *metrics])


def _faults(row: dict) -> float:
    """An episode row's ``sensor_faults`` (0 for a row written before the column, or an empty cell)."""
    v = row.get("sensor_faults")
    return float(v) if isinstance(v, (int, float)) and v == v else 0.0


def faults_total(rows: list[dict]) -> int:
    """The non-finite sensor entries replaced over all ``rows`` (meta.json's ``sensor_faults``)."""
    return int(sum(_faults(r) for r in rows))


def faults_note(rows: list[dict]) -> str:
    """One Markdown line naming, per agent whose episodes had any, the non-finite sensor entries the sensors' guard
    replaced (``sensor_faults``, av_gym/sensors/base.py: made finite, marked invalid, counted) and in how many of its
    episodes; "" when there were none (or the rows predate the column), so a clean run's page is unchanged."""
    per: dict[str, list[float]] = {}
    for r in rows:
        per.setdefault(r["agent"], []).append(_faults(r))
    hit = [f"`{a}` {sum(v):.0f} in {sum(x > 0 for x in v)} of {len(v)} episodes" for a, v in per.items() if sum(v)]
    if not hit:
        return ""
    return ("Sensor faults (non-finite readings replaced and marked invalid, `sensor_faults` in results.csv): "
            + "; ".join(hit) + ".\n")


def sensors_section(sensors: Mapping[str, dict]) -> str:
    """Markdown: per agent, the sensors preset it ran with, the fields that differ from the shipped preset, and
    the full settings (YAML, folded)."""
    import yaml

    from eval.agents import sensors_summary

    lines = ["## Sensors each agent ran with", ""]
    for label, cfg in sensors.items():
        lines.append(f"- `{label}`: {sensors_summary(cfg)}")
    lines += ["", "<details><summary>full sensor settings per agent</summary>", ""]
    for label, cfg in sensors.items():
        lines += [f"`{label}`:", "", "```yaml", yaml.safe_dump(cfg or {}, sort_keys=False).rstrip(), "```", ""]
    lines.append("</details>")
    return "\n".join(lines) + "\n"


def shields_section(shields: Mapping[str, dict]) -> str:
    """Markdown: per agent, the shield it ran behind (its preset and the fields that differ from it), which its
    label names too (:mod:`eval.labels`: ``+aeb`` for ``shield=aeb``)."""
    from eval.agents import sensors_summary

    return "\n".join(["## Shield each agent ran behind", ""]
                     + [f"- `{label}`: {sensors_summary(cfg, 'shield')}" for label, cfg in shields.items()]) + "\n"


def env_section(env: Mapping | None) -> str:
    """Markdown: the env preset the episodes ran in and every field that differs from it (``env`` as
    :func:`eval.meta.env_as_ran` records it, the same as meta.json's ``env``): ``env.track=B`` is a layout the
    table does not show."""
    if not env:
        return ""
    changed = env.get("changed") or {}
    said = ", ".join(f"{k}={v!r}" for k, v in sorted(changed.items())) if changed else ""
    return f"## Env the episodes ran in\n\n- `{env.get('preset')}`" + (f" with {said}" if said else " (as shipped)") \
        + "\n"


def checkpoints_section(checkpoints: Mapping[str, str]) -> str:
    """Markdown: the checkpoint each trained agent ran (a name like ``ppo_turn`` resolves to the newest local run
    of that config, so the table alone does not say which policy it measured)."""
    return "\n".join(["## Checkpoint each trained agent ran", ""]
                     + [f"- `{label}`: `{path}`" for label, path in checkpoints.items()]) + "\n"


def write_results(rows: list[dict], out_dir: str | Path, scenario: str, title: str,
                  sensors: Mapping[str, dict] | None = None, checkpoints: Mapping[str, str] | None = None,
                  split: str | None = None, shields: Mapping[str, dict] | None = None,
                  env: Mapping | None = None) -> str:
    """Write ``results.csv`` (every episode, every metric) and ``results.md`` (with, given ``env`` = the env as it
    ran (:func:`eval.meta.env_as_ran`), ``sensors`` = agent label → the sensors config it ran with, ``shields`` =
    label → the shield config of each shielded agent and ``checkpoints`` = label → the checkpoint a trained agent
    loaded, sections stating them); returns the Markdown table."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if split is not None:  # every row says which seed split it came from (av_gym/seeds.py)
        rows = [{**r, "split": split} for r in rows]
    columns = list(dict.fromkeys(k for r in rows for k in r))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    table = summary_table(rows, scenario)
    note = faults_note(rows)
    summary = (f"# {title}\n\nMean with 95% confidence interval over episodes, by each metric's declared kind "
               f"(av_gym/metrics/kinds.py): Wilson for rates, a seeded bootstrap for counts, durations and other "
               f"non-negative quantities, Student t for signed ones.\n\n{table}\n"
               + (f"\n{note}" if note else "")
               + (f"\n{env_section(env)}" if env else "")
               + (f"\n{checkpoints_section(checkpoints)}" if checkpoints else "")
               + (f"\n{sensors_section(sensors)}" if sensors else "")
               + (f"\n{shields_section(shields)}" if shields else ""))
    # both files replaced together or neither (a full disk could leave results.csv torn, results.md stale)
    write_texts_atomic({out / "results.csv": text.getvalue(), out / "results.md": summary}, field="out_dir")
    return table
