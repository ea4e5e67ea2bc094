"""The corpus benchmark's bar setting and its interleaved cca / PtyLab timing (no data files, no peers run)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import real_corpus  # noqa: E402  (a broken import must fail these tests, not skip them)

BETA_25, BETA_05, FIXED = ("PtyLab mPIE + pupil βP 0.25", "PtyLab mPIE + pupil βP 0.05", "PtyLab mPIE fixed pupil")


def _tool(residual, seconds, status="ok"):
    return {"status": status, "residual": {"all": residual}, "seconds": seconds}


def test_the_bar_is_the_fastest_ptylab_setting_within_the_tolerance_of_its_best():
    tools = {"cca": _tool(0.050, 1.0), BETA_25: _tool(0.0660, 122.0), BETA_05: _tool(0.0668, 34.7),
             FIXED: _tool(0.075, 10.8), "fpm-rs EPRY": _tool(0.060, 2.5)}
    assert real_corpus.bar_setting(tools) == BETA_05            # 0.0008 from the best, and faster
    tools[BETA_05] = _tool(0.0675, 34.7)
    assert real_corpus.bar_setting(tools) == BETA_25            # too far from the best now
    tools[BETA_25] = _tool(0.0, 1.0, status="failed")
    assert real_corpus.bar_setting(tools) == BETA_05            # a failed setting sets no bar
    assert real_corpus.bar_setting({"cca": _tool(0.05, 1.0), "fpm-rs EPRY": _tool(0.06, 2.0)}) is None


def test_side_by_side_alternates_the_order_and_reports_medians(monkeypatch):
    calls, cca_times, peer_times = [], iter([4.0, 5.0, 9.0]), iter([20.0, 30.0, 25.0])

    def fake_cca(data, workdir, config):
        calls.append("cca")
        return None, {"wall_s": next(cca_times)}

    def fake_peer(method, options, iterations, data, workdir, timeout):
        calls.append(("peer", iterations, options["label"]))
        return {"status": "ok", "startup_s": 1.0, "seconds": [0.5, next(peer_times) - 1.0]}

    monkeypatch.setattr(real_corpus, "run_cca", fake_cca)
    monkeypatch.setattr(real_corpus, "run_peer", fake_peer)
    out = real_corpus.side_by_side(None, Path("."), None, BETA_05, 79, 3, 60.0)
    peer = ("peer", 79, "side_by_side79")
    assert calls == ["cca", peer, peer, "cca", "cca", peer]
    assert out["cca_median_s"] == 5.0 and out["peer_median_s"] == 25.0
    assert out["ratio"] == pytest.approx(5.0)
    assert out["peer"] == BETA_05 and out["iteration"] == 79


def test_a_failed_peer_run_stops_the_comparison(monkeypatch):
    monkeypatch.setattr(real_corpus, "run_cca", lambda data, workdir, config: (None, {"wall_s": 1.0}))
    monkeypatch.setattr(real_corpus, "run_peer", lambda *a, **k: {"status": "failed", "reason": "timeout"})
    with pytest.raises(RuntimeError, match="timeout"):
        real_corpus.side_by_side(None, Path("."), None, BETA_05, 10, 2, 60.0)
