"""Shared test settings.

Tiny diffusion components live in `tests/dummies.py` (`get_dummy_components()`); fixtures that
only one module needs live in that module.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

# The suite runs as `pytest -n 2` on 2 cores: one intra-op thread per worker avoids
# oversubscription, which costs more than it gains on these tiny models.
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]

SHARED_MSTAR = Path(os.environ.get("SAR_ZERO123_MSTAR", ROOT / ".." / "shared" / "data" / "mstar")).resolve()


@pytest.fixture(scope="session")
def mstar_root() -> Path:
    """The real MSTAR folder (`../shared/data/mstar`), or skip when it is absent."""
    if not (SHARED_MSTAR / "index.csv").is_file():
        pytest.skip(f"real MSTAR data not found at {SHARED_MSTAR}")
    return SHARED_MSTAR


GLOO_PROBE = """
import datetime, torch, torch.distributed as dist
dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=30))
value = torch.ones(1)
dist.all_reduce(value)
assert value.item() == dist.get_world_size()
dist.destroy_process_group()
"""


def free_port() -> int:
    """A free TCP port on loopback for a rendezvous (29500 may be taken by another run)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def loopback_env() -> dict[str, str]:
    """Environment of a multi-process CPU run: one thread per rank, the repo importable, accelerate on
    CPU, and gloo pinned to loopback. Without GLOO_SOCKET_IFNAME gloo binds to whatever the host name
    resolves to, which in some containers is an address the other rank cannot reach (a hang)."""
    return {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": str(ROOT),
        "ACCELERATE_USE_CPU": "true",
        "GLOO_SOCKET_IFNAME": "lo",
    }


def kill_marked(marker: str) -> None:
    """SIGKILL every process whose command line contains ``marker`` (torch elastic starts ranks in their
    own sessions, so killing the launcher's process group does not reach them)."""
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if marker in cmdline.read_bytes().decode(errors="replace"):
                os.kill(int(cmdline.parent.name), signal.SIGKILL)
        except (OSError, ValueError):
            continue


def run_marked(command: list[str], log: Path, marker: str, timeout: float) -> int | None:
    """Run ``command`` with its output in ``log``; kill it and its ranks afterwards. None on timeout."""
    with log.open("w") as handle:
        process = subprocess.Popen(
            command, env=loopback_env(), stdout=handle, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            return process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        finally:
            kill_marked(marker)


@pytest.fixture
def rendezvous_port() -> int:
    """A free loopback port for a multi-process test's rendezvous."""
    return free_port()


@pytest.fixture(scope="session")
def gloo_loopback(tmp_path_factory: pytest.TempPathFactory) -> str | None:
    """Why this machine cannot form a two-process gloo group on loopback, or None when it can.

    Probed once per test session (per xdist worker) with a bare all-reduce, so that a machine whose
    networking cannot host gloo skips the multi-process tests at once instead of timing each one out.
    """
    folder = tmp_path_factory.mktemp("gloo_probe")
    probe = folder / "gloo_probe.py"
    probe.write_text(GLOO_PROBE)
    log = folder / "gloo_probe.log"
    command = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
        "--master_addr", "127.0.0.1", "--master_port", str(free_port()), str(probe),
    ]  # fmt: skip
    returncode = run_marked(command, log, str(probe), timeout=90)
    if returncode == 0:
        return None
    why = "timed out after 90 s" if returncode is None else f"exit code {returncode}"
    tail = " | ".join(log.read_text(errors="replace").strip().splitlines()[-4:])
    return f"this machine cannot form a 2-process gloo group on loopback ({why}): {tail}"


@pytest.fixture
def run_two_process(tmp_path: Path, gloo_loopback: str | None) -> Callable[..., str]:
    """Runs a two-process CPU command (gloo on loopback) and returns its output; fails the test with
    that output when the command fails or times out.

    Skips when the machine cannot form a gloo group at all (a property of the machine, like a GPU
    for the fp16 tests). The command must contain ``marker`` (a path unique to the test) so that its
    ranks can be killed afterwards.
    """
    if gloo_loopback is not None:
        pytest.skip(gloo_loopback)

    def run(command: list[str], marker: str, timeout: float = 180.0) -> str:
        log = tmp_path / "two_process.log"
        returncode = run_marked(command, log, marker, timeout)
        output = log.read_text(errors="replace")
        if returncode != 0:
            outcome = f"timed out after {timeout:.0f} s" if returncode is None else f"exit code {returncode}"
            pytest.fail(f"two-process run failed ({outcome}):\n{output[-3000:]}")
        # the teardown hazard sar_zero123.runs.checkpoints.end_run guards against, even when the race did
        # not fire
        assert "still referenced when the process group is destroyed" not in output, output[-3000:]
        return output

    return run
