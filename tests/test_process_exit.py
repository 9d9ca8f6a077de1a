"""Processes that rendered on a worker thread exit: the CPU rasterizer as a library, and ``brave6d serve``.

Where numba can use TBB (Debian's ``libtbb12``, which CI installs) its TBB threading layer hangs
at interpreter exit in ``tbb::finalize`` once a parallel kernel ran on a worker thread and TBB
sees one CPU (numba/numba#10556). Each child here is pinned to one CPU and left to choose its
own threading layer (the NUMBA_THREADING_LAYER* variables that conftest set are removed), so a
child that picks TBB hangs and the test fails within the exit deadline, not after a CI timeout.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parent.parent
COMPILE_S = 600.0  # a cold numba cache compiles the kernels first (about 35 s on 2 free cores)
EXIT_S = 30.0  # a process that finished its work must be gone by then

#: Pins the child to one CPU (TBB then starts no worker thread: the condition of the hang).
ONE_CPU = "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n"

RENDER_ON_THREAD = ONE_CPU + """
import sys, threading
import numba, torch
from brave6d.training import rasterize

def render():
    n = 64
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    rgb, _, _, _ = rasterize(means, torch.randn(n, 4, generator=g), torch.full((n, 3), 0.05),
                             torch.full((n,), 0.5), torch.rand(n, 3, generator=g), torch.eye(4)[None],
                             torch.tensor([[[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]]]), 32, 32, backend="cpu")
    assert float(rgb.sum()) > 0

worker = threading.Thread(target=render)
worker.start()
worker.join()
open(sys.argv[1], "w").write(numba.threading_layer())
"""


def _child_env(**extra: str) -> dict[str, str]:
    """The test process's environment without numba's threading settings, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return {**env, **extra}


def _wait_for_exit(proc: subprocess.Popen, done: Path) -> int:
    """Wait (at most COMPILE_S) until ``done`` exists, then at most EXIT_S for the process to end."""
    deadline = time.monotonic() + COMPILE_S
    while not done.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert done.exists(), f"the child ended (status {proc.poll()}) or timed out before it rendered"
    try:
        return proc.wait(timeout=EXIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"the child rendered on a worker thread with numba's {done.read_text()!r} threading layer "
                    f"and did not exit within {EXIT_S:.0f} s")


PIN = """
import os, sys
from brave6d.core.runtime import pin_threading_layer
pin_threading_layer()
print(os.environ.get("NUMBA_THREADING_LAYER"), os.environ.get("NUMBA_THREADING_LAYER_PRIORITY"), "numba" in sys.modules)
"""


@pytest.mark.parametrize(("requested", "layer", "priority"), [
    (None, None, "omp workqueue tbb"), ("default", "default", "omp workqueue tbb"),
    ("omp", "omp", None), ("workqueue", "workqueue", None),
    ("tbb", "omp", None), ("safe", "omp", None), ("threadsafe", "omp", None), ("forksafe", "omp", None),
])
def test_pin_threading_layer_keeps_tbb_out(requested: str | None, layer: str | None, priority: str | None) -> None:
    """The variables numba reads: OpenMP or the work queue are kept, the default and TBB-capable values are not."""
    env = _child_env(**({"NUMBA_THREADING_LAYER": requested} if requested else {}))
    done = subprocess.run([sys.executable, "-c", PIN], env=env, capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.split() == [str(layer), *str(priority).split(), "False"], done.stdout
    assert ("replaced by 'omp'" in done.stderr) == (layer != requested), done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("requested", [None, "tbb"])
def test_rasterizer_on_worker_thread_exits(tmp_path: Path, requested: str | None) -> None:
    """`from training import rasterize` pins a threading layer that cannot hang, even over an explicit 'tbb'."""
    done = tmp_path / "layer.txt"
    env = _child_env(**({"NUMBA_THREADING_LAYER": requested} if requested else {}))
    proc = subprocess.Popen([sys.executable, "-c", RENDER_ON_THREAD, str(done)], env=env, cwd=tmp_path,
                            stderr=subprocess.PIPE, text=True)
    try:
        status = _wait_for_exit(proc, done)
    finally:
        stderr = proc.stderr.read() if proc.stderr else ""
    assert status == 0, stderr[-3000:]
    assert done.read_text() in ("omp", "workqueue")
    assert ("replaced by 'omp'" in stderr) == (requested is not None), stderr[-3000:]


def _wait_until_listening(client: httpx.Client, proc: subprocess.Popen) -> None:
    """Poll ``/health`` until the server answers (it prints its address before it listens)."""
    deadline = time.monotonic() + EXIT_S
    while True:
        try:
            client.get("/health").raise_for_status()
            return
        except httpx.TransportError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve.toy_scene import make_synthetic_bundle

    return make_synthetic_bundle(tmp_path_factory.mktemp("exit_scene"), n_gaussians=2000)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serve_exits_on_signal_after_rendering(bundle_dir: Path, tmp_path: Path, sig: signal.Signals) -> None:
    """`brave6d serve` renders on its worker threads; on SIGTERM / Ctrl-C it stops promptly without a traceback.

    uvicorn shuts down, then raises the captured signal again: SIGTERM ends the process as killed
    by SIGTERM, SIGINT reaches the CLI as KeyboardInterrupt (one line, status 130), after which the
    interpreter finalises (where a TBB pool would hang)."""
    cli = ONE_CPU + "import runpy; runpy.run_module('brave6d.cli', run_name='__main__', alter_sys=True)"
    proc = subprocess.Popen([sys.executable, "-c", cli, "serve", str(bundle_dir), "--port", "0", "--device", "cpu",
                             "--log-dir", str(tmp_path / "episodes"), "--request-timeout", str(COMPILE_S)],
                            env=_child_env(), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        banner = proc.stdout.readline() if proc.stdout else ""
        match = re.search(r"on (http://127\.0\.0\.1:\d+)", banner)
        assert match, f"no banner: {banner!r} {proc.stderr.read() if proc.poll() is not None else ''}"
        url = match.group(1)
        with httpx.Client(base_url=url, timeout=COMPILE_S) as client:
            _wait_until_listening(client, proc)
            reply = client.post("/episodes", json={"width": 64, "height": 48})
            assert reply.status_code == 201, reply.text
        proc.send_signal(sig)
        status = proc.wait(timeout=EXIT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"brave6d serve did not exit within {EXIT_S:.0f} s of {sig.name} after a render")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = proc.stderr.read() if proc.stderr else ""
    assert status == {signal.SIGTERM: -signal.SIGTERM, signal.SIGINT: 130}[sig], stderr
    assert "Traceback" not in stderr, stderr


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_serve_closes_open_episodes_and_exits_within_2_s_of_a_signal(bundle_dir: Path, tmp_path: Path,
                                                                      sig: signal.Signals) -> None:
    """Issue #44's acceptance: Ctrl-C (SIGINT at its default, as in a terminal; a process started in the
    background of a non-interactive shell has it ignored) or SIGTERM on `brave6d serve` with an open
    episode: the episode's log ends with its close record, written within 2 s of the signal, and the
    process is gone within 2 s too (the console script skips the interpreter's teardown of torch and
    numba, 0.4-1.5 s on a loaded 2-core machine, once a server has stopped: brave6d.cli.console)."""
    proc = subprocess.Popen([sys.executable, "-m", "brave6d.cli", "serve", str(bundle_dir), "--port", "0", "--device",
                             "cpu", "--log-dir", str(tmp_path / "episodes")], env=_child_env(), cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        banner = proc.stdout.readline() if proc.stdout else ""
        match = re.search(r"on (http://127\.0\.0\.1:\d+)", banner)
        assert match, f"no banner: {banner!r}"
        with httpx.Client(base_url=match.group(1), timeout=COMPILE_S) as client:
            _wait_until_listening(client, proc)
            assert client.post("/episodes", json={"width": 64, "height": 48}).status_code == 201
        t0 = time.time()
        proc.send_signal(sig)
        proc.wait(timeout=EXIT_S)
        exited = time.time() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    logs = list((tmp_path / "episodes").glob("*.jsonl"))
    assert len(logs) == 1, logs
    events = [json.loads(line)["event"] for line in logs[0].read_text().splitlines()]
    assert events[-2:] == ["close", "digest"], events  # the close record, then the log's digest (issue 63)
    closed = logs[0].stat().st_mtime - t0
    assert closed <= 2.0, f"brave6d serve closed the episode {closed:.2f} s after {sig.name}"
    assert exited <= 2.0, f"brave6d serve exited {exited:.2f} s after {sig.name}"  # it skips the teardown (cli.console)
