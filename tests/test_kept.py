"""Choices measured once and kept between processes (:mod:`plenocl.io.kept`), and the FFT
route kept so (:data:`plenocl.piv.devicefft.KEPT_ROUTES`): reruns on one machine take the
same route, so their vectors agree to the bit."""

from __future__ import annotations

import json
import multiprocessing
import os

import numpy as np
import pytest

from plenocl.io.kept import CACHE_VARIABLE, KeptChoices, cache_dir
from plenocl.piv import devicefft
from plenocl.piv.correlation import correlate, window_grid


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """A kept-choices folder of this test's own."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_the_folder_is_the_variable_or_the_users_cache(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    assert cache_dir() == tmp_path
    monkeypatch.setenv(CACHE_VARIABLE, "  ")
    assert cache_dir() is None
    monkeypatch.delenv(CACHE_VARIABLE)
    assert cache_dir().name == "plenocl"


def test_the_first_value_kept_stands(folder):
    kept = KeptChoices("t", "a test choice")
    assert kept.get(("dev", 64, "host")) is None
    assert kept.keep(("dev", 64, "host"), {"route": "device"}) == {"route": "device"}
    assert kept.keep(("dev", 64, "host"), {"route": "host"}) == {"route": "device"}
    assert kept.keep(("dev", 32, "host"), {"route": "host"}) == {"route": "host"}
    other = KeptChoices("t", "a test choice")  # another process's object reads the file
    assert other.get(("dev", 64, "host")) == {"route": "device"}
    assert other.get(("dev", 32, "host")) == {"route": "host"}
    assert sorted(p.name for p in folder.iterdir()) == ["t.json", "t.lock"]  # no temporaries


def test_nothing_kept_where_the_variable_is_empty(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_VARIABLE, "")
    kept = KeptChoices("t", "a test choice")
    assert kept.keep(("k",), {"v": 1}) == {"v": 1}
    assert kept.keep(("k",), {"v": 2}) == {"v": 2}
    assert kept.get(("k",)) is None


def test_a_damaged_file_is_said_once_and_replaced(folder):
    folder.mkdir()
    (folder / "t.json").write_text("{not json")
    kept = KeptChoices("t", "a test choice")
    with pytest.warns(RuntimeWarning, match=r"could not read .*t\.json.*measured in each"):
        assert kept.get(("k",)) is None
    assert kept.keep(("k",), {"v": 1}) == {"v": 1}
    assert json.loads((folder / "t.json").read_text())["choices"] == {'["k"]': {"v": 1}}
    (folder / "t.json").write_text(json.dumps({"format": 99, "choices": {'["k"]': 5}}))
    with pytest.warns(RuntimeWarning, match="not a file of kept choices"):
        assert KeptChoices("t", "x").get(("k",)) is None


def test_a_folder_that_cannot_be_written_is_said_once(monkeypatch, tmp_path):
    """A folder that cannot be made (a file stands in its way: fails for root too)."""
    (tmp_path / "a_file").write_text("")
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "a_file" / "cache"))
    kept = KeptChoices("t", "the test's choice")
    with pytest.warns(RuntimeWarning, match=f"could not .*{CACHE_VARIABLE}") as said:
        assert kept.keep(("k",), {"v": 1}) == {"v": 1}
        assert kept.keep(("k",), {"v": 2}) == {"v": 2}
    assert len(said) == 1
    assert kept.get(("k",)) is None


def _keep_in_a_process(args):
    """One process's measurement of the same key (``value``): what stands after it."""
    path, value = args
    os.environ[CACHE_VARIABLE] = path
    return KeptChoices("race", "a raced choice").keep(("device", 64), {"value": value})


def test_processes_keeping_at_once_agree(folder):
    """Several processes measuring the same choice at once (a batch's workers starting
    together) all take the first one kept."""
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        got = pool.map(_keep_in_a_process, [(str(folder), v) for v in range(8)])
    assert len({g["value"] for g in got}) == 1
    assert KeptChoices("race", "x").get(("device", 64)) == got[0]


def _pair(shape, seed):
    rng = np.random.default_rng(seed)
    a = rng.random(shape).astype(np.float32)
    return a, np.roll(a, (1, -2, 1), axis=(0, 1, 2))


def test_a_kept_route_is_taken_by_a_new_process(queue, folder):
    """A route measured once is read by a later process instead of measured again, and a
    kept route stands over what a new measurement would say; a kept entry that names no
    route is measured again."""
    a, b = _pair((28, 30, 36), seed=3)
    grid = window_grid(a.shape, (10, 12, 18), 0.5)
    devicefft.forget_measured_routes()
    first = devicefft.FFTRoute(None, queue)
    chosen = first.correlate(a, b, grid)
    route = first.route(a, grid, False)
    assert route in ("host", "device")
    (entry,) = json.loads((folder / "fft_routes.json").read_text())["choices"].values()
    assert entry["route"] == route and entry["host_s"] > 0 and entry["device_s"] > 0

    other = "device" if route == "host" else "host"
    path = folder / "fft_routes.json"
    doc = json.loads(path.read_text())
    (key,) = doc["choices"]
    doc["choices"][key]["route"] = other  # as if an earlier process had measured that
    path.write_text(json.dumps(doc))
    devicefft.forget_measured_routes()  # as a new process
    later = devicefft.FFTRoute(None, queue)
    assert later.route(a, grid, False) == other
    got = later.correlate(a, b, grid)
    assert later.used == {other}
    want = (devicefft.DeviceCorrelation(queue).correlate(a, b, grid) if other == "device"
            else correlate(a, b, grid))
    assert np.array_equal(got.peak, want.peak)
    assert chosen.peak.shape == got.peak.shape

    doc["choices"][key]["route"] = "gpu"  # not a route: measured again and replaced
    path.write_text(json.dumps(doc))
    devicefft.forget_measured_routes()
    again = devicefft.FFTRoute(None, queue)
    assert again.route(a, grid, False) is None
    again.correlate(a, b, grid)
    (taken,) = again.used
    assert json.loads(path.read_text())["choices"][key]["route"] == taken


def test_a_standing_value_refused_is_replaced(folder):
    kept = KeptChoices("t", "a test choice")
    kept.keep(("k",), {"route": "gpu"})
    def valid(v):
        return v.get("route") in ("host", "device")
    assert kept.keep(("k",), {"route": "host"}, valid) == {"route": "host"}
    assert kept.keep(("k",), {"route": "device"}, valid) == {"route": "host"}
