"""Command line: ``mbc simulate`` and ``mbc run``.

``mbc run`` is the main job: on the embedded R6 spec and the packaged Table 2
bench data it simulates the seven WOT points at their measured spark with the
paper's combustion answer (BDUR10-90 = 24 deg, m = 6.4) and writes a
simulated-vs-measured comparison under ``results/<run-id>/``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import shutil
import sys
import time
from pathlib import Path

import pandas as pd

from . import __version__
from .bench import load_bench
from .io import read_table, write_csv, write_json, write_parquet, write_text
from .prepare import SolverSettings
from .simulate import simulate
from .spec import load_spec


def _progress(label: str):
    start = time.perf_counter()

    def show(done: int, total: int):
        width = 30
        filled = int(width * done / max(total, 1))
        el = time.perf_counter() - start
        sys.stderr.write(f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}  {el:5.1f} s")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def _solver(args) -> SolverSettings:
    return SolverSettings(step_deg=args.step_deg)


def cmd_simulate(args) -> int:
    spec = load_spec(args.spec)
    points = read_table(args.points)
    out = Path(args.out)
    res = simulate(spec, points, _solver(args), progress=_progress("simulating"))
    write_parquet(res, out)
    n_bad = int((~res["converged"]).sum())
    print(f"{len(res)} points -> {out}  ({n_bad} not converged or failed)")
    return 0


def default_run_dir(spec_hash: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("results") / f"{stamp}-{spec_hash[:8]}"


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


def _plot_comparison(cmp_: pd.DataFrame, path: Path, eta_trans: float) -> None:
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


def _plot_traces(spec, bench_row, args, path: Path) -> None:
    """Cylinder and manifold pressures over the converged cycle at one bench point."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .prepare import OperatingPoint
    from .simulate import simulate_point

    op = OperatingPoint(float(bench_row["speed_rpm"]), float(bench_row["throttle_pct"]),
                        float(bench_row["spark_deg_btdc"]), float(bench_row["lambda"]),
                        args.bdur_10_90, args.wiebe_m)
    row, _, tr = simulate_point(spec, op, _solver(args), return_traces=True)
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


def cmd_run(args) -> int:
    spec = load_spec(args.spec)
    bench = load_bench(args.bench)
    final = Path(args.out) if args.out else default_run_dir(spec.spec_hash())
    work = final.with_name(final.name + ".partial")
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    t0 = time.perf_counter()
    points = bench[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]].copy()
    points["bdur_10_90_deg"] = args.bdur_10_90
    points["wiebe_m"] = args.wiebe_m
    sim = simulate(spec, points, _solver(args), progress=_progress("simulating Table 2 points"))
    cmp_ = comparison_table(bench, sim, args.eta_trans)
    write_parquet(sim, work / "simulated.parquet")
    write_csv(cmp_, work / "comparison.csv", float_format="%.4g")
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        text = cmp_.round(2).to_string(index=False)
    write_text(text + "\n", work / "comparison.txt")
    _plot_comparison(cmp_, work / "wot_comparison.png", args.eta_trans)
    mid = bench.iloc[len(bench) // 2]
    _plot_traces(spec, mid, args, work / f"pressure_traces_{int(mid['speed_rpm'])}.png")
    write_json({
        "package_version": __version__, "engine": spec.name, "spec_hash": spec.spec_hash(),
        "bench": "packaged Table 2" if args.bench is None else str(args.bench),
        "bdur_10_90_deg": args.bdur_10_90, "wiebe_m": args.wiebe_m, "eta_trans": args.eta_trans,
        "step_deg": args.step_deg, "points": len(sim), "not_converged": int((~sim["converged"]).sum()),
        "wall_time_s": round(time.perf_counter() - t0, 2),
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
    }, work / "manifest.json")
    if final.exists():
        shutil.rmtree(final)
    work.rename(final)
    print(f"\nTable 2 (WOT, lambda 0.9), BDUR10-90 = {args.bdur_10_90:g} deg, m = {args.wiebe_m:g}, "
          f"measured torque/power divided by eta_trans = {args.eta_trans:g}:\n")
    print(text)
    print(f"\nresults: {final}/ (simulated.parquet, comparison.csv, wot_comparison.png, pressure_traces_*.png, manifest.json)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mbc", description="Model-based calibration of a restricted race engine")
    p.add_argument("--version", action="version", version=f"mbc {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
        sp.add_argument("--step-deg", type=float, default=0.5, help="crank-angle step [deg] (default 0.5)")

    s = sub.add_parser("simulate", help="simulate a table of operating points")
    s.add_argument("--points", required=True, help="CSV or Parquet with the operating-point columns")
    s.add_argument("--out", required=True, help="output Parquet file")
    common(s)
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("run", help="main job: simulate the bench points and compare with the measurements")
    r.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    r.add_argument("--out", default=None, help="output folder (default results/<run-id>/)")
    r.add_argument("--bdur-10-90", type=float, default=24.0, help="10-90 %% burn duration [deg] (default 24)")
    r.add_argument("--wiebe-m", type=float, default=6.4, help="Wiebe shape m [-] (default 6.4)")
    r.add_argument("--eta-trans", type=float, default=0.95, help="transmission efficiency [-] (default 0.95)")
    common(r)
    r.set_defaults(func=cmd_run)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"mbc: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
