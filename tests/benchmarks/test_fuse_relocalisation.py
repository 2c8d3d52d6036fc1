"""`make bench`: relocalisation against accelerometer glitches and long blackouts (issue 20's
place recognition).

The Monte Carlo's loop UAV (`tests/scenarios.py`, `simulate_loop_uav`: a 60 m diamond at
20 m/s, the filter settings of the Monte Carlo), seeds 1 .. CVSLAM_RELOC_SEEDS (5), each run
once with `fuse.relocalisation` off and once on (the same inputs):
- 30 s, the accelerometer GLITCH_M_S2 off along the body x for 1 s at each of GLITCH_AT_S
  after the start (0: no glitch);
- 60 s, the camera dark (`tests/scenarios.blackout`) over BLACKOUT_S: the vehicle comes
  back tens of metres off and too uncertain for its windows to be sure.
Printed per run: final error and RMSE (m) of each, the frames where the vehicle was lost,
CPU seconds; asserted: without a fault the two are the same to the bit and nobody is lost;
with a glitch, relocalisation ends closer (final error) on every run.
Figures: BENCHMARKS.md, "Fuse: relocalisation".
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.geometry.rotations import interpolate_positions
from tests.scenarios import (
    MC_FILTER_OVERRIDES,
    accelerometer_glitch,
    blackout,
    ekf_on_simulation,
    simulate_loop_uav,
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

SEEDS = range(1, int(os.environ.get("CVSLAM_RELOC_SEEDS", "5")) + 1)
GLITCH_AT_S = (0.0, 12.0, 20.0)
GLITCH_M_S2 = 4.0
BLACKOUT_S = (5.0, 50.0)


def _run(
    sim: Path, glitch_at_s: float, on: bool, dark_s: tuple[float, float] | None = None
) -> tuple[np.ndarray, int, float, str]:
    """(position errors (F,) m, frames lost, CPU s, the divergence if any) of one EKF run."""
    cfg = load_config((), [*MC_FILTER_OVERRIDES, f"fuse.relocalisation.enabled={on}"])
    edit = accelerometer_glitch(glitch_at_s, 1.0, GLITCH_M_S2) if glitch_at_s else None
    dark = None if dark_s is None else (lambda fs: blackout(fs, *dark_s))
    c0 = time.process_time()
    res, truth = ekf_on_simulation(sim, cfg, edit=dark, edit_inputs=edit)
    cpu = time.process_time() - c0
    tr = res.tracks["uav1"]
    e = tr.p_nav_m - interpolate_positions(truth.stamps_ns, truth.p_nav_m, tr.stamps_ns)
    d = res.divergence
    div = "" if d is None else f" diverged at {(d.stamp_ns - tr.stamps_ns[0]) * 1e-9:.1f} s"
    return np.linalg.norm(e, axis=1), sum(int(r["lost"]) for r in res.timeline), cpu, div


def test_relocalisation_after_accelerometer_glitches(tmp_path: Path) -> None:
    sims = simulate_loop_uav(tmp_path, 30.0, SEEDS)
    print("\nseed glitch_s | off: final rmse cpu | on: final rmse lost cpu")
    for seed, sim in zip(SEEDS, sims, strict=True):
        for at_s in GLITCH_AT_S:
            e_off, lost_off, cpu_off, div_off = _run(sim, at_s, False)
            e_on, lost_on, cpu_on, div_on = _run(sim, at_s, True)
            assert not (div_off or div_on)
            rmse_off, rmse_on = (float(np.sqrt(np.mean(e**2))) for e in (e_off, e_on))
            print(
                f"{seed:4d} {at_s:8.0f} | {e_off[-1]:6.2f} {rmse_off:5.2f} {cpu_off:5.1f} | "
                f"{e_on[-1]:6.2f} {rmse_on:5.2f} {lost_on:3d} {cpu_on:5.1f}"
            )
            assert lost_off == 0
            if at_s == 0:
                assert lost_on == 0
                np.testing.assert_array_equal(e_on, e_off)
            else:
                assert e_on[-1] < e_off[-1]


def test_relocalisation_after_a_long_blackout(tmp_path: Path) -> None:
    sims = simulate_loop_uav(tmp_path, 60.0, SEEDS)
    print(f"\nblackout {BLACKOUT_S[0]:g}-{BLACKOUT_S[1]:g} s")
    print("seed | off: final rmse-after cpu | on: final rmse-after lost cpu")
    for seed, sim in zip(SEEDS, sims, strict=True):
        rows = []
        for on in (False, True):
            e, lost, cpu, div = _run(sim, 0.0, on, BLACKOUT_S)
            after = e[int(10 * (BLACKOUT_S[1] + 2.0)) :]  # 10 frames a second
            rmse = float(np.sqrt(np.mean(after**2))) if len(after) else float("nan")
            lost_s = f" {lost:3d}" if on else ""
            rows.append(f"{e[-1]:6.2f} {rmse:5.2f}{lost_s} {cpu:5.1f}{div}")
        print(f"{seed:4d} | {rows[0]} | {rows[1]}")
