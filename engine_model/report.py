"""Reports of simulated vs measured points: comparison tables and figures (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from .prepare import OperatingPoint, SolverSettings
from .simulate import simulate_point


def comparison_table(bench: pd.DataFrame, sim: pd.DataFrame, eta_trans: float) -> pd.DataFrame:
    """Side-by-side simulated vs measured airflow, torque and power (torque/power at the crank = measured/eta)."""
    cmp_ = pd.DataFrame({
        "point_id": bench["point_id"].to_numpy(),
        "speed_rpm": bench["speed_rpm"].to_numpy(),
        "air_kg_h_meas": bench["air_mass_flow_kg_h"].to_numpy(),
        "air_kg_h_sim": sim["air_mass_flow_kg_h"].to_numpy(),
        "torque_nm_meas_crank": bench["brake_torque_nm"].to_numpy() / eta_trans,
        "torque_nm_sim": sim["brake_torque_nm"].to_numpy(),
        "power_kw_meas_crank": bench["brake_power_kw"].to_numpy() / eta_trans,
        "power_kw_sim": sim["brake_power_kw"].to_numpy(),
        "converged": sim["converged"].to_numpy(),
    })
    cmp_["air_err_pct"] = (cmp_["air_kg_h_sim"] / cmp_["air_kg_h_meas"] - 1) * 100
    cmp_["torque_err_pct"] = (cmp_["torque_nm_sim"] / cmp_["torque_nm_meas_crank"] - 1) * 100
    cmp_["power_err_pct"] = (cmp_["power_kw_sim"] / cmp_["power_kw_meas_crank"] - 1) * 100
    return cmp_


def plot_comparison(cmp_: pd.DataFrame, path: Path, eta_trans: float) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    n = cmp_["speed_rpm"]
    ax[0].plot(n, cmp_["air_kg_h_meas"], "ko-", label="measured")
    ax[0].plot(n, cmp_["air_kg_h_sim"], "bs--", label="simulated")
    ax[0].set_ylabel("air mass flow [kg/h]")
    ax[1].plot(n, cmp_["torque_nm_meas_crank"], "ko-", label=f"measured / {eta_trans:g}")
    ax[1].plot(n, cmp_["torque_nm_sim"], "bs--", label="simulated")
    ax[1].set_ylabel("brake torque at crank [Nm]")
    ax[2].plot(n, cmp_["power_kw_meas_crank"], "ko-", label=f"measured / {eta_trans:g}")
    ax[2].plot(n, cmp_["power_kw_sim"], "bs--", label="simulated")
    ax[2].set_ylabel("brake power at crank [kW]")
    for a in ax:
        a.set_xlabel("speed [rpm]")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("Yamaha R6 FS, WOT, lambda 0.9: uncalibrated model vs Table 2")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_traces(spec, bench_row, bdur_10_90: float, wiebe_m: float, solver: SolverSettings, path: Path) -> None:
    """Cylinder and manifold pressures over the converged cycle at one bench point."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    op = OperatingPoint(float(bench_row["speed_rpm"]), float(bench_row["throttle_pct"]),
                        float(bench_row["spark_deg_btdc"]), float(bench_row["lambda"]),
                        bdur_10_90, wiebe_m)
    row, _, tr = simulate_point(spec, op, solver, return_traces=True)
    ncyl = spec.geometry.n_cylinders
    ang = np.arange(tr.shape[1]) * 720.0 / tr.shape[1]
    fig, ax = plt.subplots(1, 2, figsize=(13, 4))
    for k in range(ncyl):
        ax[0].plot(ang, tr[k] / 1e5, lw=1, label=f"cylinder {k + 1}")
    ax[0].set_ylabel("cylinder pressure [bar]")
    ax[1].plot(ang, tr[2 * ncyl] / 1e5, label="plenum")
    ax[1].plot(ang, tr[2 * ncyl + 3] / 1e5, label="intake port 1")
    ax[1].plot(ang, tr[2 * ncyl + 4] / 1e5, label="exhaust port 1")
    ax[1].plot(ang, tr[2 * ncyl + 1] / 1e5, label="collector")
    ax[1].set_ylabel("pressure [bar]")
    for a in ax:
        a.set_xlabel("crank angle of cylinder 1 [deg], 0 = firing TDC")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(f"{op.speed_rpm:.0f} rpm WOT, spark {op.spark_deg_btdc:g} deg BTDC: pmax {row['pmax_bar']:.0f} bar "
                 f"at {row['pmax_deg_atdc']:.0f} deg ATDC, VE {row['vol_eff']:.2f}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
