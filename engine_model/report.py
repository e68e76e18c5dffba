"""Reports of simulated vs measured points: comparison tables and figures (matplotlib, Agg)."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from engine_model.io import write_figure

from engine_model.sim.prepare import OperatingPoint, SolverSettings
from engine_model.sim.simulate import simulate_point


#: Unit of a value from the suffix of its name (longest suffix first), for text meant for people.
_NAME_UNITS = (("_deg_btdc", "deg BTDC"), ("_deg_atdc", "deg ATDC"), ("_g_kwh", "g/kWh"), ("_kg_h", "kg/h"),
               ("_pct", "%"), ("_rpm", "rpm"), ("_deg", "deg"), ("_bar", "bar"), ("_kw", "kW"), ("_nm", "N m"),
               ("_m3", "m^3"), ("_m", "m"), ("_k", "K"), ("_s", "s"), ("_pa", "Pa"))


def unit_of(name: str) -> str:
    """The unit a column or spec field name carries in its suffix ('' when dimensionless)."""
    for suffix, unit in _NAME_UNITS:
        if str(name).endswith(suffix):
            return unit
    return ""


def format_value(value, name: str = "", digits: int = 3) -> str:
    """``value`` rounded to ``digits`` significant digits, with the unit its ``name`` carries (e.g. '0.216 m')."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    unit = unit_of(name)
    txt = f"{value:.{digits}g}" if value == value else "n/a"
    return f"{txt} {unit}" if unit and unit != "%" else (f"{txt} %" if unit == "%" else txt)


def bound_note(value: float, low: float, high: float, name: str = "", near: float = 0.05) -> str:
    """' (at upper bound 0.4)' when ``value`` lies within 1 % of the search range of a bound, ' (near lower
    bound 0.1 m)' within ``near`` of the range, else ''."""
    span = float(high) - float(low)
    if not span > 0 or not value == value:
        return ""
    for side, b in (("lower", low), ("upper", high)):
        d = abs(float(value) - float(b)) / span
        if d <= 0.01:
            return f" (at {side} bound {format_value(float(b), name)})"
        if d <= near:
            return f" (near {side} bound {format_value(float(b), name)})"
    return ""


def format_parameters(values: dict, bounds: dict | None = None, at_bound: dict | None = None) -> str:
    """'name = value unit' per parameter, rounded, each flagged when at (or near) its search bound.

    ``bounds``: {name: (low, high)}; ``at_bound``: {name: bool} from the fit itself (flags a parameter
    at its bound even when ``bounds`` does not give the range).
    """
    parts = []
    for k, v in values.items():
        note = ""
        if bounds and k in bounds:
            note = bound_note(v, *bounds[k], name=k)
        if not note.startswith(" (at") and at_bound and at_bound.get(k):
            note = " (at a search bound)"
        parts.append(f"{k} = {format_value(v, k)}{note}")
    return ", ".join(parts)


def format_mapping(d: dict) -> str:
    """A small dict as 'key value, key value' (no braces or quotes), numbers rounded with their units."""
    return ", ".join(f"{k} {format_value(v, str(k))}" for k, v in d.items())


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
    write_figure(fig, path, dpi=100)
    plt.close(fig)


def plot_traces(spec, bench_row, bdur_10_90: float, wiebe_m: float, solver: SolverSettings, path: Path) -> None:
    """Pressures over the converged cycle at one bench point: cylinders, manifold volumes, and the waves in intake
    runner 1 and exhaust primary 1 (1D: pipe cells; lumped: the ports), with cylinder 1's valve events shaded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from engine_model.cycle.flow import valve_lift

    op = OperatingPoint(float(bench_row["speed_rpm"]), float(bench_row["throttle_pct"]),
                        float(bench_row["spark_deg_btdc"]), float(bench_row["lambda"]),
                        bdur_10_90, wiebe_m)
    row, _, tr = simulate_point(spec, op, solver, return_traces=True)
    ncyl = spec.geometry.n_cylinders
    ang = np.arange(tr.shape[1]) * 720.0 / tr.shape[1]
    one_d = spec.gas_exchange.model == "1d"
    fig, ax = plt.subplots(1, 3, figsize=(17, 4.2))
    for k in range(ncyl):
        ax[0].plot(ang, tr[k] / 1e5, lw=1, label=f"cylinder {k + 1}")
    ax[0].set_ylabel("cylinder pressure [bar]")
    ax[1].plot(ang, tr[2 * ncyl] / 1e5, label="plenum")
    ax[1].plot(ang, tr[2 * ncyl + 3] / 1e5, label="intake port 1")
    ax[1].plot(ang, tr[2 * ncyl + 4] / 1e5, label="exhaust port 1")
    ax[1].plot(ang, tr[2 * ncyl + 1] / 1e5, label="exhaust merge" if one_d else "collector")
    ax[1].set_ylabel("pressure [bar]")
    ax[1].set_ylim(top=min(ax[1].get_ylim()[1], 3.0))
    if one_d:
        names = ("intake runner 1, middle", "intake runner 1, port end", "exhaust primary 1, port end",
                 "exhaust primary 1, middle")
        for r, name in enumerate(names):
            ax[2].plot(ang, tr[2 * ncyl + 5 + r] / 1e5, lw=1, label=name)
        ax[2].set_title("pressure waves in the pipes of cylinder 1", fontsize=9)
    else:
        ax[2].plot(ang, tr[2 * ncyl + 3] / 1e5, label="intake port 1 (lumped runners)")
        ax[2].plot(ang, tr[2 * ncyl + 4] / 1e5, label="exhaust port 1 (lumped runners)")
    ax[2].set_ylabel("pressure [bar]")
    for valves, colour in ((spec.intake_valves, "tab:blue"), (spec.exhaust_valves, "tab:red")):
        is_open = valve_lift(ang, valves) > 0.0
        ax[2].fill_between(ang, 0, 1, where=is_open, color=colour, alpha=0.08, transform=ax[2].get_xaxis_transform(),
                           label=f"{'intake' if valves is spec.intake_valves else 'exhaust'} valve 1 open")
    for a in ax:
        a.set_xlabel("crank angle of cylinder 1 [deg], 0 = firing TDC")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(f"{op.speed_rpm:.0f} rpm, throttle {op.throttle_pct:g} %, spark {op.spark_deg_btdc:g} deg BTDC: "
                 f"pmax {row['pmax_bar']:.0f} bar at {row['pmax_deg_atdc']:.0f} deg ATDC, VE {row['vol_eff']:.2f}")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)


def plot_operating_map(res: pd.DataFrame, path: Path, title: str = "") -> None:
    """Heatmaps over throttle x speed of brake torque, BMEP and knock index, with the DOE feasibility flags.

    ``res`` holds one row per (throttle_pct, speed_rpm) site with the result
    columns and, optionally, ``infeasible_reason`` from :func:`engine_model.doe.feasibility`
    (knock-limited sites marked K, near-zero-BMEP sites Z, as in the paper's Figure 1).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    th = np.sort(res["throttle_pct"].unique())
    sp = np.sort(res["speed_rpm"].unique())
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    panels = [("brake_torque_nm", "brake torque at crank [Nm]", "viridis"),
              ("bmep_bar", "BMEP [bar]", "viridis"), ("knock_index", "knock index [-] (>= 1: knock)", "magma_r")]
    for ax, (col, label, cmap) in zip(axes, panels):
        grid = res.pivot_table(index="throttle_pct", columns="speed_rpm", values=col).reindex(index=th, columns=sp)
        im = ax.imshow(grid.to_numpy(float), origin="lower", aspect="auto", cmap=cmap,
                       extent=(-0.5, len(sp) - 0.5, -0.5, len(th) - 0.5))
        fig.colorbar(im, ax=ax, label=label)
        ax.set_xticks(range(len(sp)), [f"{s / 1000:g}" for s in sp])
        ax.set_yticks(range(len(th)), [f"{t:g}" for t in th])
        ax.set_xlabel("speed [1000 rpm]")
        ax.set_ylabel("throttle [%]")
        if "infeasible_reason" in res.columns:
            for _, r in res.iterrows():
                mark = {"knock-limited": "K", "near-zero BMEP": "Z"}.get(str(r["infeasible_reason"]), "")
                if mark:
                    ax.text(int(np.searchsorted(sp, r["speed_rpm"])), int(np.searchsorted(th, r["throttle_pct"])),
                            mark, ha="center", va="center", color="w", fontsize=8, fontweight="bold")
    fig.suptitle(title or "Operating map: K = knock-limited at the MBT spark estimate, Z = near-zero BMEP")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)


def write_report(folder, name: str, title: str, sections: list) -> tuple[Path, Path]:
    """Write ``<folder>/<name>.md`` and ``<name>.html`` from a list of sections (atomically).

    Each section is ``(heading, items)``; an item is a str (a paragraph;
    Markdown-safe text), a DataFrame (a table), or a ``Path`` to a PNG in
    ``folder`` (an image, linked relatively).  Returns the two paths.
    """
    import html

    from engine_model.io import write_text

    folder = Path(folder)
    md = [f"# {title}", ""]
    ht = ["<!doctype html><html><head><meta charset='utf-8'>", f"<title>{html.escape(title)}</title>",
          "<style>body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}"
          "table{border-collapse:collapse;font-size:90%}td,th{border:1px solid #ccc;padding:2px 6px;"
          "text-align:right}img{max-width:100%}</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    for heading, items in sections:
        md += [f"## {heading}", ""]
        ht.append(f"<h2>{html.escape(heading)}</h2>")
        for it in items:
            if isinstance(it, pd.DataFrame):
                md += [it.to_markdown(index=False, floatfmt=".4g") if _has_tabulate() else
                       "```\n" + it.to_string(index=False) + "\n```", ""]
                ht.append(it.to_html(index=False, float_format=lambda v: f"{v:.4g}", border=0))
            elif isinstance(it, Path):
                rel = Path(os.path.relpath(os.path.abspath(it), os.path.abspath(folder)))
                md += [f"![{rel.stem}]({rel.as_posix()})", ""]
                ht.append(f"<p><img src='{html.escape(rel.as_posix())}' alt='{html.escape(rel.stem)}'></p>")
            else:
                md += [str(it), ""]
                ht.append(f"<p>{html.escape(str(it))}</p>")
    ht.append("</body></html>")
    p_md = write_text("\n".join(md) + "\n", folder / f"{name}.md")
    p_ht = write_text("\n".join(ht) + "\n", folder / f"{name}.html")
    return p_md, p_ht


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401
    except ImportError:
        return False
    return True


def write_index(folder, title: str, summary: list[tuple[str, str]], sections: list) -> Path:
    """Write ``<folder>/index.html``: a run's landing page linking every figure and file (atomically).

    Parameters
    ----------
    folder : path
        The run folder; every linked path must lie inside it.
    title : str
    summary : list of (label, value)
        Key figures shown as a table at the top (e.g. wall time, Ga_REL range).
    sections : list of (heading, text, paths)
        ``paths`` relative to ``folder`` (or absolute inside it); PNGs are shown
        as thumbnails linking to the full image, other files as links with their
        size.  Paths that do not exist are listed as "missing" rather than
        silently left out, so a broken stage is visible on the page.
    """
    import html

    from engine_model.io import write_text

    folder = Path(folder)
    esc = html.escape
    ht = ["<!doctype html><html><head><meta charset='utf-8'>", f"<title>{esc(title)}</title>",
          "<style>body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}"
          "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}"
          ".figs{display:flex;flex-wrap:wrap;gap:12px}.figs figure{margin:0;width:370px}"
          ".figs img{width:100%;border:1px solid #ddd}.missing{color:#b00}</style></head><body>",
          f"<h1>{esc(title)}</h1>", "<table>"]
    ht += [f"<tr><th>{esc(k)}</th><td>{esc(str(v))}</td></tr>" for k, v in summary]
    ht.append("</table>")
    for heading, text, paths in sections:
        ht.append(f"<h2>{esc(heading)}</h2>")
        if text:
            ht.append(f"<p>{esc(text)}</p>")
        figs, files = [], []
        for p in paths:
            p = Path(p)
            rel = p.relative_to(folder) if p.is_absolute() else p
            full = folder / rel
            href = esc(rel.as_posix())
            if not full.exists():
                files.append(f"<li class='missing'>{href} (missing)</li>")
            elif rel.suffix.lower() == ".png":
                figs.append(f"<figure><a href='{href}'><img src='{href}' alt='{esc(rel.stem)}'></a>"
                            f"<figcaption>{esc(rel.stem.replace('_', ' '))}</figcaption></figure>")
            else:
                size = full.stat().st_size if full.is_file() else sum(f.stat().st_size for f in full.rglob("*")
                                                                         if f.is_file())
                files.append(f"<li><a href='{href}'>{href}</a> ({size / 1024:.1f} KiB)</li>")
        if figs:
            ht.append("<div class='figs'>" + "".join(figs) + "</div>")
        if files:
            ht.append("<ul>" + "".join(files) + "</ul>")
    ht.append("</body></html>")
    return write_text("\n".join(ht) + "\n", folder / "index.html")
