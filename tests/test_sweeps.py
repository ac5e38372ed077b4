"""Sweeps: the launcher configs compose, a real multirun goes through submitit's local executor (the same code path
as SLURM, minus sbatch), and eval.sweep aggregates a multirun folder over replicates."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_module
from scipy import stats

from av_gym.metrics import bootstrap_ci
from eval.sweep import JobSetup, load_jobs, sweep_report, swept_keys


def _hydra(config: str, overrides: list[str]):
    with initialize_config_module("conf", version_base="1.3"):
        return compose(config, overrides=overrides, return_hydra_config=True).hydra


@pytest.mark.parametrize("config", ["train", "eval"])
def test_multirun_default_launcher_is_joblib_on_every_core(config):
    launcher = _hydra(config, []).launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == -1


@pytest.mark.parametrize("config", ["train", "eval"])
def test_jobs_reset_the_start_method_a_loky_worker_leaves(config, monkeypatch):
    import multiprocessing as mp

    assert _hydra(config, []).callbacks.job_setup._target_ == "eval.sweep.JobSetup"
    calls = []
    monkeypatch.setattr(mp, "set_start_method", lambda method, force=False: calls.append((method, force)))
    for method, expected in (("fork", []), (None, []), ("loky", [(None, True)])):
        monkeypatch.setattr(mp, "get_start_method", lambda allow_none=False, m=method: m)
        calls.clear()
        JobSetup().on_job_start()
        assert calls == expected, method


def test_slurm_launcher_config_extends_submitit_slurm():
    launcher = _hydra("train", ["hydra/launcher=slurm", "hydra.launcher.partition=cpu"]).launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert launcher.partition == "cpu" and launcher.cpus_per_task == 2 and launcher.timeout_min == 60
    assert _hydra("train", ["hydra/launcher=submitit_slurm"]).launcher._target_.endswith("SlurmLauncher")


@pytest.mark.slow  # submitit starts a job process per value, each importing the whole stack
def test_submitit_local_multirun_then_aggregate(tmp_path):
    """Two rule-based jobs (one short episode each) through submitit's LocalExecutor, then the sweep table."""
    sweep = tmp_path / "multirun"
    cmd = [sys.executable, "-m", "train", "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
           f"hydra.sweep.dir={sweep}", f"paths.runs={tmp_path}/runs", f"paths.checkpoints={tmp_path}/ckpt",
           "agent=always_proceed", "env.duration=2.0", "train.eval_episodes=1", "train.progress_bar=false",
           "train.eval_seed=1000007,1000008"]
    # About 5 CPU-seconds per process (the launcher and 2 parallel jobs, mostly imports). The timeout only guards
    # against a hang: on a loaded machine the wall time can stretch to minutes.
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (sweep / ".submitit").is_dir()  # it really went through submitit
    jobs, missing = load_jobs(sweep)
    assert len(jobs) == 2 and not missing
    assert swept_keys(jobs) == ["train.eval_seed"]
    result = sweep_report(sweep, plot=False)
    assert result["summary"][0]["n_seeds"] == 2 and result["summary"][0]["episodes"] == 2
    assert (sweep / "sweep.md").is_file() and (sweep / "sweep.csv").is_file()


def _fake_job(root: Path, num: int, overrides: list[str], rows: list[dict], scenario: str = "lane_keeping"):
    job = root / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"env": {"name": scenario}}))
    with open(job / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def test_sweep_groups_by_swept_values_and_gives_a_t_interval_over_seeds(tmp_path):
    rng = np.random.default_rng(0)
    expected = {}
    num = 0
    for sigma in (0.5, 1.5, 3.0):
        per_seed = []
        for seed in (0, 1, 2):
            cte = rng.uniform(0, 1, size=3) * sigma
            per_seed.append(cte.mean())
            rows = [{"agent": "pid_gnss", "episode": i, "seed": 100 * seed + i, "cte_mean_abs_m": c,
                     "lap_completed": float(i != 1)} for i, c in enumerate(cte)]
            _fake_job(tmp_path, num, ["agent=pid_gnss", f"seed={seed}", f"sensors.gnss.sigma={sigma}"], rows)
            num += 1
        expected[sigma] = per_seed
    (tmp_path / "9" / ".hydra").mkdir(parents=True)  # a job that died before writing results
    (tmp_path / "9" / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(["seed=3", "sensors.gnss.sigma=0.5"]))

    result = sweep_report(tmp_path, metrics=["cte_mean_abs_m", "lap_completed"])
    assert result["x"] == "sensors.gnss.sigma" and result["metric"] == "cte_mean_abs_m"
    assert [p.name for p in result["missing"]] == ["9"]
    assert [line["sensors.gnss.sigma"] for line in result["summary"]] == [0.5, 1.5, 3.0]
    for line in result["summary"]:
        vals = expected[line["sensors.gnss.sigma"]]
        half = stats.t.ppf(0.975, 2) * np.std(vals, ddof=1) / np.sqrt(3)
        assert line["n_seeds"] == 3 and line["episodes"] == 9
        assert line["cte_mean_abs_m"] == pytest.approx(np.mean(vals))
        assert line["cte_mean_abs_m_hi"] == pytest.approx(np.mean(vals) + half)
        assert line["lap_completed"] == pytest.approx(2 / 3)
        assert 0 < line["lap_completed_pooled_lo"] < 2 / 3 < line["lap_completed_pooled_hi"] < 1
    assert result["png"].is_file() and "| 1.5 | pid_gnss | 3 | 9 |" in result["table"]
    assert not result["warnings"]


def test_sweep_warns_when_seeds_did_not_change_the_episodes(tmp_path):
    rows = [{"agent": "always_proceed", "episode": 0, "seed": 100000, "collision": 1.0}]
    for num, seed in enumerate((0, 1)):
        _fake_job(tmp_path, num, [f"seed={seed}", "shield.detector.miss_rate=0.3"], rows, scenario="left_turn")
    _fake_job(tmp_path, 2, ["seed=0", "shield.detector.miss_rate=0.6"], rows, scenario="left_turn")
    result = sweep_report(tmp_path, plot=False)
    assert any("same metrics" in w for w in result["warnings"])
    assert not any("share some episode seeds" in w for w in result["warnings"])  # identical sets: paired


def test_sweep_warns_when_replicates_overlap(tmp_path):
    for num, seed in enumerate((0, 1)):  # python -m eval seed=0,1 episodes=2: episodes 0,1 and 1,2
        rows = [{"agent": "pid", "episode": i, "seed": seed + i, "cte_mean_abs_m": 0.1 * (seed + i + 1)}
                for i in range(2)]
        _fake_job(tmp_path, num, [f"seed={seed}"], rows)
    result = sweep_report(tmp_path, plot=False)
    assert result["summary"][0]["n_seeds"] == 2
    assert any("share some episode seeds" in w for w in result["warnings"])


def test_a_cell_with_one_replicate_shows_the_interval_over_its_episodes(tmp_path):
    """One job per swept value (no replicate key swept): the seed-to-seed interval does not exist, so the cell
    carries the interval over its episodes its kind calls for (a bootstrap for |CTE|, Wilson for a rate), and the
    table and header say so."""
    rng = np.random.default_rng(1)
    ctes = {}
    for num, sigma in enumerate((0.5, 1.5)):
        cte = rng.uniform(0, 1, size=5) * sigma
        ctes[sigma] = cte
        rows = [{"agent": "pid_gnss", "episode": i, "seed": 1000 + i, "cte_mean_abs_m": c,
                 "lap_completed": float(i != 1)} for i, c in enumerate(cte)]
        _fake_job(tmp_path, num, ["agent=pid_gnss", f"sensors.gnss.sigma={sigma}"], rows)
    result = sweep_report(tmp_path, metrics=["cte_mean_abs_m", "lap_completed"])
    for line in result["summary"]:
        cte = ctes[line["sensors.gnss.sigma"]]
        assert line["n_seeds"] == 1 and line["interval"] == "episodes"
        _, lo, hi = bootstrap_ci(cte)  # |CTE| cannot be negative (av_gym/metrics/kinds.py)
        assert (line["cte_mean_abs_m_lo"], line["cte_mean_abs_m_hi"]) == pytest.approx((lo, hi))
        assert cte.min() <= lo < cte.mean() < hi <= cte.max()
        assert (line["lap_completed_lo"], line["lap_completed_hi"]) == (line["lap_completed_pooled_lo"],
                                                                        line["lap_completed_pooled_hi"])
        assert 0 < line["lap_completed_lo"] < 0.8 < line["lap_completed_hi"] < 1
    assert "| interval |" in result["table"] and "| episodes |" in result["table"]
    assert "episode-to-episode" in result["markdown"]
