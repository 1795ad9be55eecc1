"""Choices measured once and kept between processes (:mod:`plenocl.io.kept`), and the FFT
route kept so (:data:`plenocl.piv.devicefft.KEPT_ROUTES`): reruns on one machine take the
same route, so their vectors agree to the bit."""

from __future__ import annotations

import json
import multiprocessing
import os
import warnings

import numpy as np
import pytest

from plenocl.io.kept import CACHE_VARIABLE, FORMAT, KeptChoices, cache_dir
from plenocl.opencl import build
from plenocl.opencl.build import source_digest
from plenocl.piv import devicefft
from plenocl.piv.correlation import correlate, window_grid


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """A kept-choices folder of this test's own."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "cache"))
    return tmp_path / "cache"


def _file(folder, name="t"):
    return folder / f"{name}.v{FORMAT}.json"


def _valid(value) -> bool:
    return isinstance(value, dict) and value.get("route") in ("host", "device")


def test_the_folder_is_the_variable_or_the_users_cache(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    assert cache_dir() == tmp_path
    monkeypatch.setenv(CACHE_VARIABLE, "~/kept")
    assert cache_dir() == cache_dir().expanduser() and cache_dir().is_absolute()
    monkeypatch.setenv(CACHE_VARIABLE, "  ")
    assert cache_dir() is None
    monkeypatch.delenv(CACHE_VARIABLE)
    assert cache_dir().name == "plenocl" and cache_dir().is_absolute()


def test_a_choice_is_measured_once_and_then_read(folder):
    kept = KeptChoices("t", "a test choice")
    calls = []

    def measure(route):
        return lambda: calls.append(route) or {"route": route}

    assert kept.get(("dev", 64, "host")) is None
    assert kept.choose(("dev", 64, "host"), measure("device")) == {"route": "device"}
    assert kept.choose(("dev", 64, "host"), measure("host")) == {"route": "device"}
    assert kept.choose(("dev", np.int64(32), "host"), measure("host")) == {"route": "host"}
    assert calls == ["device", "host"]  # the second call of a key measured nothing
    other = KeptChoices("t", "a test choice")  # another process's object reads the file
    assert other.get(("dev", 64, "host")) == {"route": "device"}
    assert other.get(("dev", 32, "host")) == {"route": "host"}  # NumPy's int as Python's
    assert sorted(p.name for p in folder.iterdir()) == [_file(folder).name, "t.v1.lock"]


def test_nothing_kept_where_the_variable_is_empty(monkeypatch):
    monkeypatch.setenv(CACHE_VARIABLE, "")
    kept = KeptChoices("t", "a test choice")
    assert kept.choose(("k",), lambda: {"v": 1}) == {"v": 1}
    assert kept.choose(("k",), lambda: {"v": 2}) == {"v": 2}
    assert kept.get(("k",)) is None


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"choices": 5}', "[" * 200000])
def test_a_damaged_file_is_said_and_replaced(folder, text):
    folder.mkdir()
    _file(folder).write_text(text)
    kept = KeptChoices("t", "a test choice")
    with pytest.warns(RuntimeWarning, match=r"t\.v1\.json.*replaced.*measured by the process"):
        assert kept.get(("k",)) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert kept.choose(("k",), lambda: {"v": 1}) == {"v": 1}
    assert json.loads(_file(folder).read_text())["choices"] == {'["k"]': {"v": 1}}


def test_a_standing_value_refused_is_measured_again_and_replaced(folder):
    kept = KeptChoices("t", "a test choice")
    kept.choose(("k",), lambda: {"route": "gpu"})
    assert kept.get(("k",), _valid) is None
    assert kept.choose(("k",), lambda: {"route": "host"}, _valid) == {"route": "host"}
    assert kept.choose(("k",), lambda: {"route": "device"}, _valid) == {"route": "host"}


def test_a_folder_that_cannot_be_written_is_said(monkeypatch, tmp_path):
    """A folder that cannot be made (a file stands in its way: fails for root too)."""
    (tmp_path / "a_file").write_text("")
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "a_file" / "cache"))
    kept = KeptChoices("t", "the test's choice")
    with pytest.warns(RuntimeWarning, match=f"could not keep it .*{CACHE_VARIABLE}"):
        assert kept.choose(("k",), lambda: {"v": 1}) == {"v": 1}
    assert kept.get(("k",)) is None


def _choose_in_a_process(path, barrier, own, shared):
    """One process choosing its own key and a shared one, started with the others."""
    os.environ[CACHE_VARIABLE] = path
    kept = KeptChoices("race", "a raced choice")
    barrier.wait()
    kept.choose(("own", own), lambda: {"value": own})
    return kept.choose(("shared",), lambda: {"value": shared})


def _worker(path, barrier, own, queue):
    queue.put(_choose_in_a_process(path, barrier, own, own))


def test_processes_choosing_at_once_agree_and_lose_nothing(folder):
    """Processes started together (a batch's workers): every process's own key is kept
    (no update lost) and all take the first value kept for the shared key."""
    spawn = multiprocessing.get_context("spawn")
    count = 4
    barrier, results = spawn.Barrier(count), spawn.Queue()
    procs = [spawn.Process(target=_worker, args=(str(folder), barrier, n, results))
             for n in range(count)]
    for p in procs:
        p.start()
    got = [results.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=60)
    assert len({g["value"] for g in got}) == 1
    kept = KeptChoices("race", "x")
    assert all(kept.get(("own", n)) == {"value": n} for n in range(count))


def _pair(shape, seed):
    rng = np.random.default_rng(seed)
    a = rng.random(shape).astype(np.float32)
    return a, np.roll(a, (1, -2, 1), axis=(0, 1, 2))


def test_a_kept_route_is_taken_by_a_new_process(queue, folder):
    """A route measured once is read by a later process instead of measured again, and a
    kept route stands over what a new measurement would say; a kept entry that is not a
    route (a hand-edited file) is measured again and replaced; padded windows of the
    same box are another measurement."""
    a, b = _pair((28, 30, 36), seed=3)
    grid = window_grid(a.shape, (10, 12, 18), 0.5)
    devicefft.forget_measured_routes()
    first = devicefft.FFTRoute(None, queue)
    first.correlate(a, b, grid)
    route = first.route(a, grid, False)
    assert route in ("host", "device")
    path = _file(folder, "fft_routes")
    (key, entry), = json.loads(path.read_text())["choices"].items()
    assert entry["route"] == route and entry["host_s"] > 0 and entry["device_s"] > 0
    assert queue.device.driver_version.strip() in key and '"unpadded"' in key
    assert source_digest(devicefft.PROGRAM) in key  # a changed FFT kernel measures again

    def kept_as(value):
        doc = json.loads(path.read_text())
        doc["choices"][key] = value  # as if an earlier process had measured that
        path.write_text(json.dumps(doc))
        devicefft.forget_measured_routes()  # as a new process
        return devicefft.FFTRoute(None, queue)

    other = "device" if route == "host" else "host"
    later = kept_as({**entry, "route": other})
    assert later.route(a, grid, False) == other
    got = later.correlate(a, b, grid)
    assert later.used == {other}
    want = (devicefft.DeviceCorrelation(queue).correlate(a, b, grid) if other == "device"
            else correlate(a, b, grid))
    assert np.array_equal(got.peak, want.peak)
    for bad in ({**entry, "route": "gpu"}, {**entry, "host_s": None},
                {**entry, "device_s": "fast"}, [route]):
        again = kept_as(bad)
        assert again.route(a, grid, False) is None
        again.correlate(a, b, grid)  # measured again, not a crash
        (taken,) = again.used
        assert json.loads(path.read_text())["choices"][key]["route"] == taken
    assert first.route(a, grid, True) is None  # padded: not the unpadded box's route


def _route_in_a_process(device, path, gain, barrier, results):
    """A new process's first FFT route for one box, with a margin that makes its own
    measurement choose ``host`` (gain 0) or ``device`` (gain 1e9)."""
    os.environ[CACHE_VARIABLE] = path
    from plenocl import get_queue
    from plenocl.opencl.device import devices_by_preference

    chosen = [d for d in devices_by_preference()
              if (d.platform.name.strip(), d.name.strip()) == device]
    queue = get_queue(chosen[0])
    devicefft.DEVICE_GAIN = gain
    a, b = _pair((24, 26, 30), seed=4)
    route = devicefft.FFTRoute(None, queue)
    timed, calls = route._timed, []
    route._timed = lambda *args: calls.append(1) or timed(*args)  # counts measurements
    barrier.wait()
    route.correlate(a, b, window_grid(a.shape, (12, 12, 16), 0.5))
    results.put((sorted(route.used), len(calls)))


def test_new_processes_measuring_at_once_take_one_route(queue, folder):
    """Processes whose own measurements would disagree (forced), started together, all
    take one route from their first call: one measures, the others wait and read its
    choice (no two measurements timed against each other)."""
    spawn = multiprocessing.get_context("spawn")
    device = (queue.device.platform.name.strip(), queue.device.name.strip())
    gains = (0.0, 1e9, 0.0, 1e9)
    barrier, results = spawn.Barrier(len(gains)), spawn.Queue()
    procs = [spawn.Process(target=_route_in_a_process,
                           args=(device, str(folder), g, barrier, results)) for g in gains]
    for p in procs:
        p.start()
    got = [results.get(timeout=300) for _ in procs]
    for p in procs:
        p.join(timeout=60)
    assert len({tuple(used) for used, _ in got}) == 1 and len(got[0][0]) == 1
    assert sum(calls for _, calls in got) == 1


def test_a_programs_digest_follows_its_source_and_its_headers(tmp_path, monkeypatch):
    """The digest a measured route is kept under changes with the program's text and with
    each header it includes, at any depth, and not with a file it does not include."""
    texts = {"a.cl": '#include "b.h"\n  # include "c.h" /* two */\nkernel void k() {}\n',
             "b.h": '#include "d.h"\n#define B 1\n', "c.h": "#define C 2\n",
             "d.h": "#define D 3\n", "e.h": "#define E 4\n"}
    for name, text in texts.items():
        (tmp_path / name).write_text(text)
    monkeypatch.setattr(build, "kernel_dir", lambda: tmp_path)

    def digest():
        source_digest.cache_clear()
        return source_digest("a.cl")

    seen = [digest()]
    for name in ("e.h", "a.cl", "b.h", "c.h", "d.h"):
        (tmp_path / name).write_text(texts[name] + "/* changed */\n")
        seen.append(digest())
    source_digest.cache_clear()
    assert seen[1] == seen[0]  # e.h is not included
    assert len(set(seen[1:])) == 5
