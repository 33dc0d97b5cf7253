"""`bench posetrace`: the per-scan trace of `bench inproc --pose-trace` and where it is read."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.tools.bench import posetrace as pt


def straight_run(n: int = 401, turn_from: float = 5.0, turn_to: float = 10.0,
                 turn: float = 0.05) -> dict[str, np.ndarray]:
    """20 m along x at 0.05 m a scan. Odometry is the truth; the estimate's heading error
    grows by ``turn`` [rad] between ``turn_from`` and ``turn_to`` [m] of travel and stays."""
    x = np.linspace(0.0, 20.0, n)
    truth = np.column_stack((x, np.zeros(n), np.zeros(n)))
    h = turn * np.clip((x - turn_from) / (turn_to - turn_from), 0.0, 1.0)
    y = np.concatenate(([0.0], np.cumsum(np.sin(h[:-1]) * np.diff(x))))  # drifting sideways
    est = np.column_stack((x, y, h))
    return {"t": x / 0.5, "odom": truth.copy(), "truth": truth, "estimate": est,
            "matched": np.ones(n, np.int8), "score": np.full(n, 0.9),
            "conditioning": np.full(n, 0.5)}


def test_the_stretch_where_the_estimate_turned_is_ranked_first():
    tr = straight_run()
    parts = pt.stretches(tr, 5.0)
    assert len(parts) == 5  # 0-5, 5-10, 10-15, 15-20 and the last scan's own piece
    # each within its scans: the 4 steps from one stretch to the next are in neither
    assert sum(p.travel for p in parts) == pytest.approx(20.0 - 4 * 0.05)
    first = pt.worst(parts, 1)[0]
    assert first.start_xy[0] == pytest.approx(5.0) and first.end_xy[0] < 10.0
    assert first.heading_change == pytest.approx(0.05, abs=0.005)  # the ends' means
    assert first.odom_heading_change == 0.0  # odometry did not turn: the matcher did
    assert first.matched == 1.0 and first.conditioning == pytest.approx(0.5)
    s = pt.summary(tr)
    assert s["heading_max_rad"] == pytest.approx(0.05)
    assert s["pose_max_m"] == pytest.approx(float(np.abs(tr["estimate"][:, 1]).max()))
    lines = pt.report(tr, 5.0, 2)
    # the figures, the weakly pinned scans (none here), the table's two heads, two rows
    assert "trusted matches 100.0 %" in lines[0] and len(lines) == 6
    assert "(conditioning < 0.15): 0 %; 0 runs" in lines[1]


def test_where_the_scans_pin_no_along_track_position_the_estimate_is_odometry():
    """Two corridors of 100 scans whose conditioning is below degenerate_ratio. Odometry
    measures each step 4 % long there (0.2 m over the 5 m); the estimate keeps it in the
    first and not in the second. A weak run shorter than 20 scans does not count."""
    tr = straight_run()
    step = np.zeros(len(tr["t"]))
    step[101:201] = step[251:351] = 0.002  # [m] added to the steps that end at those scans
    tr["odom"][:, 0] += np.cumsum(step)
    tr["estimate"] = tr["truth"].copy()
    tr["estimate"][:, 0] += np.cumsum(np.where(np.arange(len(step)) < 240, step, 0.0))
    tr["conditioning"][100:201] = tr["conditioning"][250:351] = 0.05
    tr["conditioning"][380:390] = 0.05
    runs = pt.weak_stretches(tr, 0.15)
    assert [(a, b) for a, b, _, _ in runs] == [(100, 200), (250, 350)]
    assert runs[0][2] == pytest.approx(0.2) and runs[0][3] == pytest.approx(0.2)
    assert runs[1][2] == pytest.approx(0.0) and runs[1][3] == pytest.approx(0.2)
    line = pt.report(tr, 5.0, 1)[1]
    assert "(conditioning < 0.15): 53 %; 2 runs of 20" in line  # 212 of 401 scans
    assert "RMS 0.141 m (odometry's 0.200 m" in line
    tr["matched"][:] = -1  # no localizer: no such line
    assert not any("pinned" in ln for ln in pt.report(tr, 5.0, 1))


def test_a_run_without_the_localizer_has_no_match_figures():
    tr = straight_run()
    tr["matched"][:] = -1
    tr["score"][:] = tr["conditioning"][:] = math.nan
    assert math.isnan(pt.summary(tr)["matched"])
    assert all(math.isnan(p.matched) and math.isnan(p.conditioning)
               for p in pt.stretches(tr, 5.0))
    assert "trusted matches -" in pt.report(tr, 5.0, 1)[0]


@pytest.mark.parametrize("damage", ["missing", "shape", "nan", "text"])
def test_a_file_that_is_no_trace_is_one_clear_error(tmp_path, damage, capsys):
    f = tmp_path / "t.npz"
    tr = straight_run(21)
    if damage == "missing":
        del tr["matched"]
    elif damage == "shape":
        tr["truth"] = tr["truth"][:, :2]
    elif damage == "nan":
        tr["estimate"][3, 0] = math.nan
    if damage == "text":
        f.write_text("not a trace")
    else:
        np.savez(f, **tr)
    with pytest.raises(pt.TraceError):
        pt.load_trace(f)
    assert pt.main([str(f)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "posetrace" in err


def test_the_in_process_runner_writes_the_trace_it_reports(tmp_path, capsys):
    """`bench inproc --pose-trace DIR`: one row per scan, the figures of the run's report."""
    from topoexplore.tools.bench.inproc import run

    f = tmp_path / "paper-room.npz"
    r = run("paper-room", "reliability", 0,
            ("sim.odom_drift=0.05", "sim.odom_drift_heading=0.05", "localizer.enabled=true"),
            30.0, pose_trace=f)
    tr = pt.load_trace(f)
    n = len(tr["t"])
    assert n == pytest.approx(r["sim_time_s"] * 5.0, abs=2)  # a scan every 0.2 s
    assert np.all(np.diff(tr["t"]) > 0)
    s = pt.summary(tr)
    assert s["pose_rms_m"] == pytest.approx(r["pose_rms_m"], abs=1e-4)
    assert s["heading_max_rad"] == pytest.approx(r["heading_max_rad"], abs=1e-5)
    assert tr["matched"][0] == -1 and (tr["matched"][1:] >= 0).all()  # no map before scan 0
    assert pt.main([str(f), "--worst", "3"]) == 0
    assert "stretches of 5 m" in capsys.readouterr().out
    # the replay of the run's own scans with its own parameters is the run, bit for bit
    tr = pt.load_trace(f, replay=True)
    again = pt.replay(tr, [])
    for k in ("estimate", "matched", "odom", "truth"):
        assert np.array_equal(again[k], tr[k]), k
    assert np.array_equal(again["score"], tr["score"], equal_nan=True)
    other = pt.replay(tr, ["localizer.directional=false", "localizer.sigma=0.1"])
    assert not np.array_equal(other["estimate"], tr["estimate"])
    assert np.array_equal(other["truth"], tr["truth"])  # the same path
    assert pt.main([str(f), str(f), "--replay", "--set", "localizer.sigma=0.1"]) == 0
    out = capsys.readouterr().out
    assert out.count("replayed RMS") == 2 and "geometric mean over 2 trace(s)" in out


def test_a_replay_needs_the_localizer_and_its_scans(tmp_path, capsys):
    from topoexplore.tools.bench.inproc import run

    f = tmp_path / "off.npz"
    run("dead-end", "frontier", 0, (), 5.0, pose_trace=f)
    tr = pt.load_trace(f, replay=True)
    assert (tr["matched"] == -1).all()
    with pytest.raises(pt.TraceError, match="localizer is off"):
        pt.replay(tr, [])
    assert len(pt.replay(tr, ["localizer.enabled=true"])["t"]) == len(tr["t"])
    no_scans = tmp_path / "no-scans.npz"
    np.savez(no_scans, **straight_run(21))
    assert pt.main([str(no_scans)]) == 0  # enough to read
    capsys.readouterr()
    for args in ([str(no_scans), "--replay"], [str(f), "--set", "localizer.sigma=0.1"],
                 [str(f), "--replay", "--set", "localizer.sigma=-1"], [str(tmp_path / "none")]):
        assert pt.main(args) == 2, args
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "posetrace" in err, (args, err)


def test_a_reader_that_stops_early_gets_no_traceback(tmp_path):
    """`topoexplore bench posetrace F | head -1`: the pipe closes under the report, and the
    command ends quietly (exit 141, as a shell's own broken pipe), not with a traceback."""
    import subprocess
    import sys

    f = tmp_path / "t.npz"
    np.savez(f, **straight_run(4001))  # a report of about 400 kB, more than a pipe holds
    p = subprocess.Popen([sys.executable, "-m", "topoexplore.tools.cli", "bench", "posetrace",
                          str(f), "--stretch", "0.01", "--worst", "100000"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout.read(100)
    p.stdout.close()
    err = p.stderr.read().decode()
    p.stderr.close()
    assert p.wait(timeout=60) == 141 and "Traceback" not in err, err
