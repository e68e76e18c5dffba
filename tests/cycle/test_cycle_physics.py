"""Physics of the cycle kernel: analytic limits and conservation, on the real engine kernel."""

import dataclasses

import pytest

from engine_model import OperatingPoint, SolverSettings, default_spec, simulate_point, wiebe
from engine_model.thermo import constant_cp_gas_set


def _otto_spec():
    """The R6 with IVC and EVO moved to BDC, and no wall heat transfer: an Otto cycle between BDCs."""
    s = default_spec()
    iv = dataclasses.replace(s.intake_valves, close_deg=540.0)
    ev = dataclasses.replace(s.exhaust_valves, open_deg=180.0,
                             close_deg=s.exhaust_valves.open_deg + s.exhaust_valves.duration_deg)
    ht = dataclasses.replace(s.heat_transfer, multiplier=0.0)
    return s.replace(intake_valves=iv, exhaust_valves=ev, heat_transfer=ht)


@pytest.mark.parametrize("gamma", [1.3, 1.4])
def test_ideal_otto_efficiency(gamma):
    """Constant gamma, adiabatic, burn of ~1 deg centred on TDC: eta within 0.5 % of 1 - r^(1-gamma)."""
    spec = _otto_spec()
    far, heat = 0.06, 1.5e6        # fuel/air ratio [-], heat per kg mixture [J/kg] (keeps peak T inside the 4400 K table range)
    gas = constant_cp_gas_set(gamma, 287.0, heat, far)
    bdur_10_90, m = 0.5, 2.0
    bdur = wiebe.bdur_10_90_to_bdur(bdur_10_90, m)
    soc = wiebe.soc_for_ca50(0.0, bdur, m)
    op = OperatingPoint(6000.0, 100.0, soc, 1.0, bdur_10_90, m)
    row, _ = simulate_point(spec, op, SolverSettings(step_deg=0.1, max_cycles=12, min_cycles=3), gas=gas)
    q_in = row["fuel_burned_mg_per_cycle"] * 1e-6 * (1 + far) / far * heat
    eta = row["gross_work_j_per_cycle"] / q_in
    eta_otto = 1.0 - spec.geometry.compression_ratio ** (1.0 - gamma)
    assert eta == pytest.approx(eta_otto, rel=5e-3)


def test_motored_cycle_peaks_at_tdc_without_knock():
    spec = default_spec()
    op = OperatingPoint(6000.0, 100.0, 30.0, 1.0, 24.0, 6.4, motored=True)
    row, _ = simulate_point(spec, op)
    assert row["converged"]
    # heat loss moves the motored peak slightly before TDC; 1 deg is the bound
    assert abs(row["pmax_deg_atdc"]) <= 1.0
    assert row["knock_index"] == 0.0
    assert row["fuel_mass_flow_kg_h"] == 0.0
    # compression alone: well above ambient, far below a fired cycle
    assert 20.0 < row["pmax_bar"] < 45.0
    assert row["imep_net_bar"] < 0.0      # a motored engine absorbs work


@pytest.fixture(scope="module")
def wot_9000():
    spec = default_spec()
    op = OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4)
    return simulate_point(spec, op)[0]


def test_conservation_on_converged_cycle():
    """Whole-engine balances over the last cycle: in - out (mass) and in - out - work - heat (energy).

    The cycle-to-cycle criterion includes the mass balance, so it is run here at
    a tolerance 10x tighter than the 0.1 % the issue asks for; the energy balance
    is not part of any criterion and is an independent check of the scheme.
    """
    spec = default_spec()
    op = OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4)
    row, _ = simulate_point(spec, op, SolverSettings(tolerance=1e-4, max_cycles=200))
    assert row["converged"]
    assert row["mass_balance_error"] < 1e-3
    assert row["energy_balance_error"] < 5e-3


def test_rich_mixture_releases_less_than_lhv(wot_9000):
    """At lambda 0.9 part of the fuel energy stays in CO and H2: fuel-to-work chain stays below ideal."""
    eta_ind = wot_9000["imep_gross_bar"] * 1e5 * default_spec().geometry.total_displacement_m3 / (
        wot_9000["fuel_mass_flow_kg_h"] / 3600 / (9000 / 120) * default_spec().fuel.lhv_j_per_kg)
    eta_otto = 1 - 12.8 ** (1 - 1.3)
    assert 0.25 < eta_ind < eta_otto


def test_step_halving_changes_torque_and_airflow_little():
    spec = default_spec()
    op = OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4)
    tight = dict(tolerance=1e-5, max_cycles=200)
    a, _ = simulate_point(spec, op, SolverSettings(step_deg=0.5, **tight))
    b, _ = simulate_point(spec, op, SolverSettings(step_deg=0.25, **tight))
    assert a["converged"] and b["converged"]
    assert a["brake_torque_nm"] == pytest.approx(b["brake_torque_nm"], rel=3e-3)
    assert a["air_mass_flow_kg_h"] == pytest.approx(b["air_mass_flow_kg_h"], rel=3e-3)


def test_very_late_burn_is_a_result_not_a_failure(wot_9000):
    """A burn still going at EVO (CA50 ~100 deg ATDC) leaves mixture unburned: lower power, converged."""
    spec = default_spec()
    row, _ = simulate_point(spec, OperatingPoint(9000.0, 100.0, 50.0, 0.9, 50.0, 8.0))
    assert row["status"] == "ok" and row["converged"]
    assert row["ca50_deg_atdc"] > 90.0
    assert row["brake_power_kw"] < 0.5 * wot_9000["brake_power_kw"]
    assert row["exhaust_temp_k"] > wot_9000["exhaust_temp_k"]


def test_failure_codes_name_the_volume():
    from engine_model.sim.simulate import failure_text
    assert failure_text(201, 4) == "negative mass in cylinder 2"
    assert failure_text(110, 4) == "temperature left the 150-4400 K range in exhaust port 3"
    assert failure_text(212, 4) == "negative mass in plenum"


def _with_segments(spec, n_in, n_ex):
    """The lumped gas exchange (the fast option) with ``n_in`` / ``n_ex`` segments per runner."""
    return spec.replace(intake=dataclasses.replace(spec.intake, runner_segments=n_in),
                        exhaust=dataclasses.replace(spec.exhaust, runner_segments=n_ex),
                        gas_exchange=dataclasses.replace(spec.gas_exchange, model="lumped"))


@pytest.mark.parametrize("n_in,n_ex", [(1, 1), (2, 3), (4, 1)])
def test_segmented_runners_keep_the_gas_volume(n_in, n_ex):
    """Splitting a runner into segments redistributes its gas volume, never creates or loses any."""
    from engine_model.sim.prepare import kernel_inputs
    spec = _with_segments(default_spec(), n_in, n_ex)
    it, ex, ncyl = spec.intake, spec.exhaust, spec.geometry.n_cylinders
    ki = kernel_inputs(spec, OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4))
    assert ki.vfix.size == 3 * ncyl + 3 + ncyl * (n_in - 1 + n_ex - 1)
    runner = lambda s: ncyl * 3.141592653589793 / 4 * s.runner_diameter_m**2 * s.runner_length_m  # noqa: E731
    expected = (ncyl * (it.port_volume_m3 + ex.port_volume_m3) + it.plenum_volume_m3 + it.throttle_body_volume_m3
                + ex.collector_volume_m3 + runner(it) + runner(ex))
    assert ki.vfix[ncyl:].sum() == pytest.approx(expected, rel=1e-12)


def test_segmented_runner_converges_in_the_number_of_segments():
    """Lumped option: the segments discretise a pipe, refining 2 -> 4 segments moves airflow by little.

    One segment (the plain Helmholtz lumping) is not converged: it misplaces the
    runner's own compliance.
    """
    spec = default_spec()
    op = OperatingPoint(7000.0, 100.0, 45.0, 0.9, 24.0, 6.4)
    ve = {n: simulate_point(_with_segments(spec, n, n), op)[0]["vol_eff"] for n in (1, 2, 4)}
    assert ve[2] == pytest.approx(ve[4], rel=0.03)
    assert abs(ve[1] / ve[4] - 1.0) > abs(ve[2] / ve[4] - 1.0)


def test_runner_joint_failures_are_named():
    from engine_model.sim.simulate import failure_text
    # 4 cylinders, 2 intake and 3 exhaust segments: volumes 15..18 intake joints, 19..26 exhaust joints
    assert failure_text(215, 4, 2, 3) == "negative mass in intake runner 1, joint 1"
    assert failure_text(218, 4, 2, 3) == "negative mass in intake runner 4, joint 1"
    assert failure_text(122, 4, 2, 3) == "temperature left the 150-4400 K range in exhaust runner 2, joint 2"
