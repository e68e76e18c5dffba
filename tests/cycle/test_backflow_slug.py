"""The intake runners' backflow slug (``intake.runner_backflow_slug``).

A lumped runner has no gas volume of its own, so without the slug the gas a
port pushes back mixes into the whole plenum.  The slug keeps it in the
runner's plenum-side share and returns it first.  The reference for what the
plenum should hold is the same runner split into 8 segments (a discretisation
of the 1D pipe in which the backflow stays near the valve whatever the
backflow model; docs/sections/speed.md, fifth round).
"""

import numpy as np
import pytest

from engine_model import OperatingPoint, SolverSettings, default_spec, simulate_point
from engine_model.cycle import layout as L

WOT_8000 = OperatingPoint(8000.0, 100.0, 49.4, 0.9, 24.0, 6.4)      # Table 2: the strongest backflow at WOT
LOW_LOAD = OperatingPoint(3500.0, 25.0, 25.0, 1.0, 24.0, 6.4)       # throttled: backflow into the ports every cycle
LOW_SPEED_WOT = OperatingPoint(3042.0, 95.0, 30.0, 0.9, 24.0, 6.4)  # pulsation pushes gas back out through the restrictor


def _spec(slug, nseg=1):
    return default_spec().with_values({"intake.runner_backflow_slug": slug, "intake.runner_segments": nseg,
                                       "exhaust.runner_segments": nseg})


def _plenum_bulk(spec, state):
    """Masses [kg] of air, mixture and products in the plenum node outside the slugs, and the slugs (ncyl, NSLUG)."""
    vol, mr, _ = state
    ncyl = spec.geometry.n_cylinders
    nflow = ncyl * (spec.intake.runner_segments + spec.exhaust.runner_segments)
    slugs = mr[nflow:].reshape(ncyl, L.NSLUG)
    plenum = vol[3 * ncyl, :3]
    return plenum - slugs[:, :3].sum(axis=0), slugs


def _burned_fraction(spec, state):
    bulk, _ = _plenum_bulk(spec, state)
    return bulk[2] / bulk.sum()


@pytest.fixture(scope="module")
def wot_8000_runs():
    return {name: simulate_point(spec, WOT_8000) for name, spec in
            (("slug", _spec(True)), ("mixed", _spec(False)), ("8 segments", _spec(False, 8)))}


def test_plenum_holds_what_a_finely_segmented_runner_leaves_there(wot_8000_runs):
    """Burned gas in the plenum's bulk: the slug lands within 0.3 points of the 8-segment runner; mixing does not."""
    y = {name: _burned_fraction(_spec(name == "slug", 8 if name == "8 segments" else 1), run[1])
         for name, run in wot_8000_runs.items()}
    assert all(r[0]["converged"] for r in wot_8000_runs.values())
    assert abs(y["slug"] - y["8 segments"]) < 0.003, y
    assert y["mixed"] - y["8 segments"] > 0.02, y      # the lumping artefact the slug removes


def test_slug_ledgers_stay_inside_the_plenum():
    """Every slug species >= 0, together no more than the node holds, and no slug beyond its room (+ ramp)."""
    spec = _spec(True)
    for op in (WOT_8000, LOW_LOAD, LOW_SPEED_WOT):
        row, state = simulate_point(spec, op)
        assert row["converged"], op
        bulk, slugs = _plenum_bulk(spec, state)
        vol = state[0]
        plenum = vol[3 * spec.geometry.n_cylinders]
        assert (slugs[:, :3] >= 0.0).all()
        assert (bulk >= -1e-12 * plenum[:3].sum()).all(), bulk
        # room of a slug [m3]: the runner's plenum-side gas share; the node's density turns it into kg
        room = ((1.0 - spec.intake.runner_volume_at_port) * np.pi / 4 * spec.intake.runner_diameter_m**2
                * spec.intake.runner_length_m)
        rho = plenum[:3].sum() / (spec.intake.plenum_volume_m3 + spec.geometry.n_cylinders * room)
        assert (slugs[:, :3].sum(axis=1) <= 1.05 * room * rho).all(), slugs[:, :3].sum(axis=1) / (room * rho)


@pytest.mark.parametrize("op", [LOW_LOAD, LOW_SPEED_WOT], ids=["low load", "low speed WOT"])
def test_conservation_with_the_slug_where_backflow_is_strongest(op):
    """Mass and energy close over the converged cycle (the slug is a ledger inside the plenum node)."""
    row, _ = simulate_point(_spec(True), op, SolverSettings(tolerance=1e-4, max_cycles=200))
    assert row["converged"]
    assert row["mass_balance_error"] < 1e-3
    assert row["energy_balance_error"] < 5e-3


def test_long_run_with_the_slug_is_periodic_at_low_load():
    """No noise floor: 150 plain cycles at the low-load point settle to a cycle that repeats to 1e-7."""
    spec = _spec(True)
    long = SolverSettings(max_cycles=150, min_cycles=150, accelerate=False)
    ref, state = simulate_point(spec, LOW_LOAD, long)
    again, _ = simulate_point(spec, LOW_LOAD, SolverSettings(max_cycles=2, min_cycles=2, accelerate=False),
                              state=state)
    assert again["trapped_mass_mg"] == pytest.approx(ref["trapped_mass_mg"], rel=1e-7)
    assert again["imep_net_bar"] == pytest.approx(ref["imep_net_bar"], rel=1e-7)
