"""Global map-wide model: recovery of the truth law, CV family choice, uncertainty, persistence, spec check."""

import json

import numpy as np
import pandas as pd
import pytest

from engine_model import default_spec

from engine_model import doe
from engine_model import priors
from engine_model.bench.burnlaw import BurnLaw
from engine_model.globalmodel.mapmodel import MapModel, fit_map_model, kfold_indices

FACTORS3 = ("throttle_pct", "speed_rpm", "spark_deg_btdc")
LAW = BurnLaw()


def around_mbt(n, seed, lo=-20.0, hi=5.0):
    """Sobol points over throttle 5-100 % x 3000-13000 rpm, spark lo..hi deg around the MBT prior."""
    p = doe.sobol(n, bounds={"spark_deg_btdc": (lo, hi)}, seed=seed)
    p["spark_deg_btdc"] = p["spark_deg_btdc"] + priors.spark_estimate(p["speed_rpm"].to_numpy(),
                                                                   p["throttle_pct"].to_numpy())
    return p


def identified(n, seed, sb=1.0, sm=0.3):
    p = around_mbt(n, seed)
    y = LAW.predict(p)
    rng = np.random.default_rng(seed + 100)
    p["bdur_10_90_deg"] = y["bdur_10_90_deg"] + sb * rng.standard_normal(n)
    p["wiebe_m"] = y["wiebe_m"] + sm * rng.standard_normal(n)
    return p


def synthetic(n, f, noise, seed):
    r = np.random.default_rng(seed)
    d = pd.DataFrame({"throttle_pct": r.uniform(5, 100, n), "speed_rpm": r.uniform(3000, 13000, n),
                      "spark_deg_btdc": r.uniform(10, 60, n), "lambda": 0.9})
    x = np.column_stack([(d.throttle_pct - 52.5) / 47.5, (d.speed_rpm - 8000) / 5000, (d.spark_deg_btdc - 35) / 25])
    y = f(x)
    d["bdur_10_90_deg"] = y + noise * r.standard_normal(n)
    d["wiebe_m"] = 5.0 + 0.1 * x[:, 0] + noise * r.standard_normal(n)
    return d, y


@pytest.fixture(scope="module")
def fitted():
    train = identified(64, 0)
    return train, MapModel(factors=FACTORS3).fit(train, spec=default_spec())


#: Noise seeds of the recovery check.  Measured over seeds 0-11: held-out RMSE against the law 0.50-0.86 deg /
#: 0.13-0.26 (BDUR10-90 / m), z-score RMS 0.76-1.55 / 0.65-1.35, CV RMSE 1.05-1.56 / 0.31-0.44.
RECOVERY_SEEDS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def recovery():
    test = around_mbt(512, 99)
    y = LAW.predict(test)
    rows = []
    for seed in RECOVERY_SEEDS:
        m = MapModel(factors=FACTORS3).fit(identified(64, seed), spec=default_spec())
        p = m.predict(test)
        row = {"seed": seed, "extrapolated": p["extrapolation"].mean(), "std_scale": min(m.std_scale_.values()),
               "std_scale_max": max(m.std_scale_.values())}
        for o, short in (("bdur_10_90_deg", "b"), ("wiebe_m", "m")):
            e = p[o] - y[o]
            row[f"rmse_{short}"] = float(np.sqrt(np.mean(e ** 2)))
            row[f"z_{short}"] = float(np.sqrt(np.mean((e / p[f"{o}_std"]) ** 2)))
            row[f"cv_{short}"] = min(m.cv_rmse_[o].values())
        rows.append(row)
    return pd.DataFrame(rows)


def test_recovers_the_truth_law_below_the_identification_noise(recovery):
    """64 Sobol points with identification noise sigma = 1.0 deg (BDUR) and 0.3 (m): a model that averages the
    noise instead of following it predicts the *truth* on unseen points better than one identification does,
    i.e. held-out RMSE < sigma, on every seed (12-seed worst: 0.86 deg, 0.26)."""
    d = recovery
    assert (d["rmse_b"] < 1.0).all() and (d["rmse_m"] < 0.3).all(), d
    assert d["rmse_b"].mean() < 0.85 and d["rmse_m"].mean() < 0.25, d
    # the CV error estimates the error against *noisy* data: about sqrt(sigma^2 + model error^2)
    assert d["cv_b"].between(0.9, 1.8).all() and d["cv_m"].between(0.27, 0.5).all(), d


def test_stated_uncertainty_is_about_right(recovery):
    """z-score RMS of the model's own std against the truth: within 0.5-2 on every seed and 0.7-1.5 on average
    (1 would be perfect).  The raw polynomial std (coefficient uncertainty of a model assumed correct) gave
    2.3 / 1.5 on seed 0; the CV calibration (``std_scale_``) brings it to 1.55 / 0.65 there."""
    d = recovery
    for c in ("z_b", "z_m"):
        assert d[c].between(0.5, 2.0).all() and 0.7 <= d[c].mean() <= 1.5, d
    assert (d["std_scale"] >= 0.5).all() and (d["std_scale_max"] <= 5.0).all(), d
    # test points beyond the 64 training points' box are flagged (a few, near the edges of the space)
    assert ((d["extrapolated"] > 0) & (d["extrapolated"] < 0.2)).all(), d


def test_noise_free_data_is_reproduced_closely():
    train = identified(64, 1, sb=0.0, sm=0.0)
    m = MapModel(factors=FACTORS3).fit(train)
    test = around_mbt(256, 7)
    err = m.predict(test)["bdur_10_90_deg"] - LAW.predict(test)["bdur_10_90_deg"]
    assert np.sqrt(np.mean(err**2)) < 0.5  # interpolation error only, over a 35-45 deg spread... see next line
    assert LAW.predict(test)["bdur_10_90_deg"].std() > 4.0  # (the law varies by several degrees: not trivial)


def test_cv_chooses_the_family_that_fits():
    # an exact cubic: the PRESS-selected polynomial recovers it, the GP only approximates it
    cubic = lambda x: 25 + 3 * x[:, 0] - 2 * x[:, 1] + 1.5 * x[:, 0] * x[:, 1] - x[:, 2] ** 2 + 0.8 * x[:, 0] ** 3
    d, _ = synthetic(60, cubic, 0.05, 0)
    m = MapModel(factors=FACTORS3, spark_reference="absolute").fit(d)
    assert m.chosen_["bdur_10_90_deg"] == "poly"
    assert m.cv_rmse_["bdur_10_90_deg"]["poly"] < 0.1
    # a local bump no low-order polynomial can follow: the GP wins
    bump = lambda x: 25 + 8 * np.exp(-((x[:, 0] - 0.3) ** 2 + (x[:, 1] + 0.2) ** 2) / (2 * 0.15**2))
    d, _ = synthetic(60, bump, 0.05, 0)
    m = MapModel(factors=FACTORS3, spark_reference="absolute").fit(d)
    assert m.chosen_["bdur_10_90_deg"] == "gp"
    assert m.cv_rmse_["bdur_10_90_deg"]["gp"] < 0.6 * m.cv_rmse_["bdur_10_90_deg"]["poly"]
    t = m.cv_table()
    assert set(t.columns) == {"output", "family", "cv_rmse", "chosen"} and t["chosen"].sum() == 2


def test_save_load_round_trip_and_spec_check(fitted, tmp_path):
    train, m = fitted
    path = m.save(tmp_path / "model.json")
    assert not list(tmp_path.glob(".*.tmp"))
    spec = default_spec()
    m2 = MapModel.load(path, spec=spec)
    test = around_mbt(32, 3)
    pd.testing.assert_frame_equal(m.predict(test), m2.predict(test))
    assert m2.chosen_ == m.chosen_ and m2.spec_hash_ == spec.spec_hash() and m2.std_scale_ == m.std_scale_
    other = spec.with_values({"geometry.compression_ratio": 12.0})
    with pytest.raises(ValueError, match=r"model\.json: .*fitted for engine spec .* not for spec"):
        MapModel.load(path, spec=other)
    with pytest.raises(ValueError, match="not for spec"):
        m.check_spec(other)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "something else"}))
    with pytest.raises(ValueError, match="not a map model file"):
        MapModel.load(bad)
    with pytest.raises(ValueError, match="not found"):
        MapModel.load(tmp_path / "missing.json")
    # the table builder's loader reads it too, and refuses it for another engine
    from engine_model.tables import settings as maps
    assert maps.load_model(path).chosen_ == m.chosen_
    with pytest.raises(ValueError, match="not for spec"):
        maps.check_model(maps.load_model(path), other)


def test_extrapolation_flag_and_fixed_factors(fitted):
    _, m = fitted
    assert "lambda" not in m.ranges_
    p = pd.DataFrame({"throttle_pct": [50.0, 50.0], "speed_rpm": [8000.0, 14500.0],
                      "spark_deg_btdc": [40.0, 60.0], "lambda": 1.0})
    assert list(m.predict(p)["extrapolation"]) == [False, True]
    # clamp (default): far outside the box the prediction is the value at the box edge, not a runaway cubic
    far = pd.DataFrame({"throttle_pct": 50.0, "speed_rpm": 8000.0, "spark_deg_btdc": [40.0, 80.0, 89.0],
                        "lambda": 1.0})
    pf = m.predict(far)
    assert pf["extrapolation"].tolist()[1:] == [True, True]
    assert pf["bdur_10_90_deg"].iloc[1] == pytest.approx(pf["bdur_10_90_deg"].iloc[2])
    # lambda constant in the data -> recorded; another lambda is an extrapolation
    d, _ = synthetic(30, lambda x: 20 + x[:, 0], 0.01, 1)
    m2 = MapModel(spark_reference="absolute", families=("poly",)).fit(d)
    assert m2.fixed_factors_ == {"lambda": 0.9}
    q = d.iloc[:2][["throttle_pct", "speed_rpm", "spark_deg_btdc"]].assign(**{"lambda": [0.9, 1.0]})
    assert list(m2.predict(q)["extrapolation"]) == [False, True]


def test_failed_identifications_are_excluded_and_listed():
    d = identified(40, 2)
    d["point_id"] = [f"id{i}" for i in range(40)]
    d.loc[[3, 7], "bdur_10_90_deg"] = np.nan
    m = fit_map_model(d, factors=FACTORS3, families=("poly",))
    assert m.excluded_ == ["id3", "id7"] and m.n_points_ == 38


def test_bad_input():
    d = identified(20, 0)
    with pytest.raises(ValueError, match="unknown/empty families"):
        MapModel(families=("svm",)).fit(d)
    with pytest.raises(ValueError, match="lack output"):
        MapModel().fit(d.drop(columns=["wiebe_m"]))
    with pytest.raises(ValueError, match="need >= 6"):
        MapModel().fit(d.iloc[:4])
    with pytest.raises(ValueError, match="not fitted"):
        MapModel().predict(d)


def test_kfold_indices_partition():
    folds = kfold_indices(23, 5, 0)
    allidx = np.sort(np.concatenate(folds))
    assert np.array_equal(allidx, np.arange(23)) and len(folds) == 5
    assert all(len(f) in (4, 5) for f in folds)


# --------------------------------------------------------------------------- load coordinate, output transform

def _toy_load_table(spec_hash=None):
    """A load table with a known, steep-then-flat shape (no simulation): pi = 1 - 0.8 exp(-t/20) - 2e-5 n/1000."""
    from engine_model.globalmodel.load_table import LoadTable
    t = (5.0, 10.0, 20.0, 30.0, 40.0, 60.0, 80.0, 100.0)
    n = (2000.0, 5000.0, 8000.0, 11000.0, 14000.0)
    v = [[1 - 0.8 * np.exp(-a / 20.0) - 0.02 * b / 1000.0 for b in n] for a in t]
    return LoadTable(t, n, v, quantity="plenum_pressure_ratio", spec_hash=spec_hash)


def test_load_table_interpolates_refuses_bad_grids_and_round_trips():
    from engine_model.globalmodel.load_table import LoadTable
    lt = _toy_load_table()
    # PCHIP reproduces the nodes exactly and is monotone between them (the function is monotone in throttle)
    np.testing.assert_allclose(lt(np.array(lt.throttle_pct), 8000.0), lt.array[:, 2], rtol=1e-12)
    fine = lt(np.linspace(5, 100, 400), 6500.0)
    assert np.all(np.diff(fine) > 0)
    exact = 1 - 0.8 * np.exp(-np.linspace(5, 100, 400) / 20.0) - 0.02 * 6.5
    assert np.max(np.abs(fine - exact)) < 0.01          # interpolation error of an 8-node PCHIP, well below the spread
    assert list(lt.covers([50, 50, 3], [8000, 15000, 8000])) == [True, False, False]
    assert LoadTable.from_dict(lt.to_dict()) == lt
    with pytest.raises(ValueError, match=r"LoadTable.speed_rpm: duplicate breakpoint 5000 rpm at positions 1 and 2"):
        LoadTable((0, 10, 20, 30), (1000, 5000, 5000, 9000), np.ones((4, 4)))
    with pytest.raises(ValueError, match=r"throttle 10 %, speed 5000 rpm: nan is not a finite number > 0"):
        v = np.ones((4, 4)); v[1, 1] = np.nan
        LoadTable((0, 10, 20, 30), (1000, 5000, 7000, 9000), v)
    with pytest.raises(ValueError, match=r"shape \(3, 4\), expected \(4, 4\)"):
        LoadTable((0, 10, 20, 30), (1000, 5000, 7000, 9000), np.ones((3, 4)))
    with pytest.raises(ValueError, match=r"quantity = 'boost'"):
        LoadTable((0, 10, 20, 30), (1000, 5000, 7000, 9000), np.ones((4, 4)), quantity="boost")


def test_model_with_load_table_uses_load_and_checks_spec_and_coverage(tmp_path):
    spec = default_spec()
    lt = _toy_load_table(spec.spec_hash())
    train = identified(64, 0)
    m = MapModel(factors=FACTORS3, load_table=lt).fit(train, spec=spec)
    assert "load" in m.ranges_ and "throttle_pct" not in m.ranges_
    lo, hi = m.ranges_["load"]
    lt_train = lt(train["throttle_pct"], train["speed_rpm"])
    assert lo == pytest.approx(lt_train.min()) and hi == pytest.approx(lt_train.max())
    # two throttles with the same load (same speed) get the same prediction: the model sees load, not throttle
    a = pd.DataFrame({"throttle_pct": [60.0], "speed_rpm": [8000.0], "spark_deg_btdc": [40.0], "lambda": [0.9]})
    lt_flat = type(lt)(lt.throttle_pct, lt.speed_rpm, np.where(np.array(lt.throttle_pct)[:, None] >= 60, 0.9,
                                                                lt.array), spec_hash=spec.spec_hash())
    m_flat = MapModel(factors=FACTORS3, load_table=lt_flat, spark_reference="absolute").fit(train, spec=spec)
    b = a.assign(throttle_pct=[80.0])
    np.testing.assert_allclose(m_flat.predict(a)["bdur_10_90_deg"], m_flat.predict(b)["bdur_10_90_deg"])
    # recovery of the truth law as with throttle (64 points, noise 1.0 / 0.3): below the noise on new points
    test = around_mbt(256, 99)
    test = test[test["throttle_pct"] >= 5.0]
    p, y = m.predict(test), LAW.predict(test)
    assert np.sqrt(np.mean((p["bdur_10_90_deg"] - y["bdur_10_90_deg"]) ** 2)) < 1.0
    assert np.sqrt(np.mean((p["wiebe_m"] - y["wiebe_m"]) ** 2)) < 0.3
    # outside the table's grid: flagged
    out = a.assign(speed_rpm=[15000.0])
    assert bool(m.predict(out)["extrapolation"].iloc[0])
    # saved and loaded with the table; old-format (version 1) files still load
    path = m.save(tmp_path / "m.json")
    m2 = MapModel.load(path, spec=spec)
    pd.testing.assert_frame_equal(m.predict(test), m2.predict(test))
    assert m2.load_table == lt
    # a table of another engine, data outside the table, wrong type: refused with the reason
    other = spec.with_values({"geometry.compression_ratio": 12.0})
    with pytest.raises(ValueError, match=r"LoadTable: simulated for engine spec .* not for spec"):
        MapModel(factors=FACTORS3, load_table=lt).fit(train, spec=other)
    wide = train.assign(speed_rpm=np.where(np.arange(len(train)) == 5, 14500.0, train["speed_rpm"]))
    with pytest.raises(ValueError, match=r"data row 5 \(throttle .* speed 14500 rpm\) lies outside the load table"):
        MapModel(factors=FACTORS3, load_table=lt).fit(wide, spec=spec)
    with pytest.raises(ValueError, match=r"load_table must be an engine_model.globalmodel.load_table.LoadTable"):
        MapModel(load_table={"a": 1}).fit(train)


def test_version_1_model_file_still_loads(fitted, tmp_path):
    _, m = fitted
    d = m.to_dict()
    d["version"] = 1
    for k in ("load_table", "output_transform"):
        d.pop(k)
    p = tmp_path / "v1.json"
    p.write_text(json.dumps(d))
    test = around_mbt(16, 5)
    pd.testing.assert_frame_equal(MapModel.load(p).predict(test), m.predict(test))


def test_log_output_transform_is_positive_and_recovers_the_law():
    train = identified(64, 0)
    m = MapModel(factors=FACTORS3, output_transform="log").fit(train)
    test = around_mbt(512, 99)
    p, y = m.predict(test), LAW.predict(test)
    assert np.sqrt(np.mean((p["bdur_10_90_deg"] - y["bdur_10_90_deg"]) ** 2)) < 1.0
    assert np.sqrt(np.mean((p["wiebe_m"] - y["wiebe_m"]) ** 2)) < 0.3
    # CV errors are reported in the output's own unit (comparable with the untransformed model's)
    assert 0.9 < min(m.cv_rmse_["bdur_10_90_deg"].values()) < 1.6
    # far outside the data a log-model stays positive even when extended
    far = pd.DataFrame({"throttle_pct": 50.0, "speed_rpm": 8000.0, "spark_deg_btdc": [-30.0, 90.0], "lambda": 1.0})
    mx = MapModel(factors=FACTORS3, output_transform="log", extrapolation="extend").fit(train)
    assert (mx.predict(far)[["bdur_10_90_deg", "wiebe_m"]].to_numpy() > 0).all()
    with pytest.raises(ValueError, match=r"output_transform='log' needs wiebe_m > 0; row 3"):
        MapModel(factors=FACTORS3, output_transform="log").fit(train.assign(
            wiebe_m=np.where(np.arange(len(train)) == 3, -0.5, train["wiebe_m"])))
    with pytest.raises(ValueError, match=r"output_transform = 'sqrt'"):
        MapModel(output_transform="sqrt").fit(train)


def test_linear_extrapolation_continues_the_edge_slope_then_holds():
    # y = 20 + 3 x_spark exactly (coded): linear continuation reproduces it beyond the box, up to half the range
    d, _ = synthetic(40, lambda x: 20 + 3 * x[:, 2], 0.0, 3)
    m = MapModel(factors=FACTORS3, spark_reference="absolute", families=("poly",), extrapolation="linear").fit(d)
    lo, hi = m.ranges_["spark_deg_btdc"]
    half = 0.5 * (hi - lo)
    s = np.array([hi + 0.2 * half, hi + 0.9 * half, hi + half + 1.0, 90.0])
    assert s[2] < 90.0
    pts = pd.DataFrame({"throttle_pct": 50.0, "speed_rpm": 8000.0, "spark_deg_btdc": s, "lambda": 0.9})
    got = m.predict(pts)["bdur_10_90_deg"].to_numpy()
    # synthetic() codes spark as (s - 35) / 25; the continuation reaches half the training range beyond the edge
    np.testing.assert_allclose(got, 20 + 3 * (np.minimum(s, hi + half) - 35) / 25, atol=1e-6)
    assert got[2] == pytest.approx(got[3])                 # flat beyond one coded unit
    assert m.predict(pts)["extrapolation"].all()


# --------------------------------------------------------------------------- phasing parametrisation

def _ridge_identified(n, seed, sm=0.6):
    """Identifications whose m is off by N(0, sm) and whose BDUR10-90 trades along the iso-phasing ridge: the
    CA50 offset (ignition-to-CA50 angle) is the truth's exactly, BDUR10-90 follows from it and the noisy m."""
    from engine_model.globalmodel.mapmodel import bdur_10_90_from_ca50_offset, ca50_offset_deg
    p = around_mbt(n, seed)
    y = LAW.predict(p)
    off = ca50_offset_deg(y["bdur_10_90_deg"].to_numpy(), y["wiebe_m"].to_numpy())
    m = y["wiebe_m"].to_numpy() + sm * np.random.default_rng(seed + 200).standard_normal(n)
    return p.assign(wiebe_m=m, bdur_10_90_deg=bdur_10_90_from_ca50_offset(off, m))


def test_ca50_offset_helpers_invert_each_other_and_match_wiebe():
    from engine_model import wiebe
    from engine_model.globalmodel.mapmodel import bdur_10_90_from_ca50_offset, ca50_offset_deg
    b, m = np.array([15.0, 24.5, 40.0]), np.array([2.0, 6.2, 7.0])
    off = ca50_offset_deg(b, m)
    # CA50 of a burn from a 35 deg BTDC spark lies at offset - 35 deg ATDC (eq 5 of the paper)
    np.testing.assert_allclose(wiebe.burn_angles(35.0, b, m)["ca50_deg_atdc"], off - 35.0, rtol=1e-12)
    np.testing.assert_allclose(bdur_10_90_from_ca50_offset(off, m), b, rtol=1e-12)
    assert np.all(np.diff(ca50_offset_deg(24.5, np.array([2.0, 4.0, 6.0]))) > 0)   # at fixed BDUR10-90: longer


def test_phasing_parametrisation_keeps_the_phasing_when_errors_lie_on_the_ridge():
    from engine_model.globalmodel.mapmodel import ca50_offset_deg
    train = _ridge_identified(64, 0)
    test = around_mbt(256, 99)
    y = LAW.predict(test)
    off_true = ca50_offset_deg(y["bdur_10_90_deg"].to_numpy(), y["wiebe_m"].to_numpy())
    ph = MapModel(factors=FACTORS3, parametrisation="phasing").fit(train)
    bm = MapModel(factors=FACTORS3).fit(train)
    pp, pb = ph.predict(test), bm.predict(test)
    assert list(pp.columns[:4]) == ["bdur_10_90_deg", "bdur_10_90_deg_std", "wiebe_m", "wiebe_m_std"]
    assert set(ph.chosen_) == {"ca50_offset_deg", "wiebe_m"} and "ca50_offset_deg_std" in pp.columns
    # the predicted outputs are one Wiebe burn: the reported offset is the (BDUR10-90, m) burn's own
    np.testing.assert_allclose(ca50_offset_deg(pp["bdur_10_90_deg"], pp["wiebe_m"]), pp["ca50_offset_deg"],
                               rtol=1e-9)
    rmse = lambda e: float(np.sqrt(np.mean(np.square(e))))
    e_ph = rmse(pp["ca50_offset_deg"] - off_true)
    e_bm = rmse(ca50_offset_deg(pb["bdur_10_90_deg"].to_numpy(), pb["wiebe_m"].to_numpy()) - off_true)
    # fitted separately, BDUR10-90 and m each average their (correlated) noise and the phasing they imply is off;
    # fitted as (offset, m) the phasing error is only the surface's own.  Measured: 0.72 vs 3.53 deg.
    assert e_ph < 0.4 * e_bm, (e_ph, e_bm)
    # m is fitted the same way in both parametrisations
    np.testing.assert_allclose(pp["wiebe_m"], pb["wiebe_m"], rtol=1e-9)


def test_phasing_model_round_trip_old_files_and_bad_input(tmp_path):
    spec = default_spec()
    train = _ridge_identified(40, 1)
    m = MapModel(factors=FACTORS3, parametrisation="phasing", families=("poly",)).fit(train, spec=spec)
    path = m.save(tmp_path / "ph.json")
    d = json.loads(path.read_text())
    assert d["version"] == 3 and d["parametrisation"] == "phasing"
    test = around_mbt(16, 5)
    pd.testing.assert_frame_equal(MapModel.load(path, spec=spec).predict(test), m.predict(test))
    # a version-2 file (no parametrisation) is a BDUR10-90/m model
    m2 = MapModel(factors=FACTORS3, families=("poly",)).fit(train, spec=spec)
    d2 = m2.to_dict()
    d2["version"] = 2
    d2.pop("parametrisation")
    (tmp_path / "v2.json").write_text(json.dumps(d2))
    old = MapModel.load(tmp_path / "v2.json", spec=spec)
    assert old.parametrisation == "bdur_m"
    pd.testing.assert_frame_equal(old.predict(test), m2.predict(test))
    d["parametrisation"] = "ca90"
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"bad\.json: parametrisation 'ca90' is not one of"):
        MapModel.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match=r"parametrisation = 'ca90'"):
        MapModel(parametrisation="ca90").fit(train)
    with pytest.raises(ValueError, match=r"parametrisation='phasing' needs outputs"):
        MapModel(parametrisation="phasing", outputs=("wiebe_m",)).fit(train)
    # outside the Wiebe domain (offset <= 0 or m <= -1, reachable by an untransformed surface far out): no burn
    got = m.burn_from_phasing({"ca50_offset_deg": np.array([50.0, -1.0, 50.0]), "ca50_offset_deg_std": np.ones(3),
                           "wiebe_m": np.array([5.0, 5.0, -1.5]), "wiebe_m_std": np.ones(3)})
    assert np.isfinite(got["bdur_10_90_deg"][0]) and np.isnan(got["bdur_10_90_deg"][1:]).all()
    with pytest.raises(ValueError, match=r"row 2: bdur_10_90_deg = -1, wiebe_m = 5.4"):
        MapModel(parametrisation="phasing").fit(train.assign(
            bdur_10_90_deg=np.where(np.arange(len(train)) == 2, -1.0, train["bdur_10_90_deg"])))
