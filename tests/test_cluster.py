"""What ``--ray``, ``--hosts`` and ``--distributed`` refuse, before anything runs: a Ray
address that does not answer or is not Ray's, options that contradict each other, and the
cluster's environment read for the host index. The sweeps and the tuning run on a local Ray
cluster are test_sweeps_rollouts.py's and test_tune_rollouts.py's (slow)."""

import socket
import threading
import time

import pytest

from safewbc_jax.app.cli import hosts_from_env, main
from safewbc_jax.sweeps import cluster

SPEC = """
[sweep]
scenario = "arms"
duration = 0.05

[grid]
"poles.left_fist.p1" = [5.0, 20.0]
"""


@pytest.fixture
def spec(tmp_path):
    p = tmp_path / "tiny.toml"
    p.write_text(SPEC)
    return p


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def http_port():
    """A local TCP server that answers as HTTP/1.1 does (not gRPC): a port that is open but
    is no Ray head."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)

    def serve():
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            with c:
                c.recv(64)
                c.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

    threading.Thread(target=serve, daemon=True).start()
    yield srv.getsockname()[1]
    srv.close()


@pytest.mark.parametrize("command", ["sweep", "tune"])
def test_a_bad_ray_address_fails_in_seconds_naming_it(spec, tmp_path, http_port, capsys,
                                                      command):
    out = tmp_path / ("d" if command == "sweep" else "t.toml")
    closed = f"127.0.0.1:{_free_port()}"
    for address, needle in ((closed, f"--ray {closed}: cannot connect to 127.0.0.1 port"),
                            (f"127.0.0.1:{http_port}", "answers, but not as a Ray head"),
                            ("headnode", "--ray 'headnode': expected HOST:PORT")):
        t0 = time.perf_counter()
        rc = main([command, str(spec), "--out", str(out), "--ray", address])
        err = capsys.readouterr().err
        # a connection refused or a wrong answer: milliseconds; the limit leaves room
        # for the spec's parsing on a loaded machine, far below Ray's own minutes
        assert time.perf_counter() - t0 < 10.0
        assert rc == 2 and needle in err, err
        assert not out.exists()                         # nothing written


def test_ray_refuses_options_of_the_other_engines(spec, tmp_path, capsys):
    out = str(tmp_path / "d")
    assert main(["sweep", str(spec), "--out", out, "--ray", "--hosts", "2"]) == 2
    assert "--ray with 2 hosts: Ray schedules every chunk itself" in capsys.readouterr().err
    assert main(["sweep", str(spec), "--out", out, "--ray", "--engine", "mujoco",
                 "--workers", "1"]) == 2
    assert "--workers 1 with --ray" in capsys.readouterr().err


def test_check_address_accepts_auto_and_rejects_bad_ports():
    cluster.check_address("auto")        # Ray's own lookup of a running cluster
    for bad in ("host:0", "host:99999", "host:port", ":6379", "ray://host"):
        with pytest.raises(cluster.ClusterError, match="expected HOST:PORT"):
            cluster.check_address(bad)


@pytest.mark.parametrize("env, expected", [
    # a job array --array=0-3: four hosts
    ({"SLURM_ARRAY_TASK_ID": "2", "SLURM_ARRAY_TASK_COUNT": "4",
      "SLURM_ARRAY_TASK_MIN": "0"}, (4, 2)),
    # --array=10-18:4 (ids 10, 14, 18): three hosts, id 14 is the second
    ({"SLURM_ARRAY_TASK_ID": "14", "SLURM_ARRAY_TASK_COUNT": "3",
      "SLURM_ARRAY_TASK_MIN": "10", "SLURM_ARRAY_TASK_STEP": "4"}, (3, 1)),
    # srun -n 8: the job step's tasks (an array's variables win where both are set)
    ({"SLURM_NTASKS": "8", "SLURM_PROCID": "7"}, (8, 7)),
])
def test_distributed_reads_the_host_index_from_slurm(env, expected):
    assert hosts_from_env(env) == expected


def test_distributed_names_what_is_missing_or_wrong(spec, tmp_path, capsys, monkeypatch):
    with pytest.raises(ValueError, match="found neither a SLURM job array"):
        hosts_from_env({"HOME": "/root"})
    with pytest.raises(ValueError, match="SLURM_PROCID='x' is not an integer"):
        hosts_from_env({"SLURM_NTASKS": "2", "SLURM_PROCID": "x"})
    with pytest.raises(ValueError, match="host index 4 of 4 hosts"):
        hosts_from_env({"SLURM_NTASKS": "4", "SLURM_PROCID": "4"})
    for k in [k for k in __import__("os").environ if k.startswith("SLURM_")]:
        monkeypatch.delenv(k)
    out = str(tmp_path / "d")
    assert main(["sweep", str(spec), "--out", out, "--distributed"]) == 2
    assert "give --hosts N --host-index I instead" in capsys.readouterr().err
    monkeypatch.setenv("SLURM_NTASKS", "2")
    monkeypatch.setenv("SLURM_PROCID", "0")
    assert main(["sweep", str(spec), "--out", out, "--distributed", "--hosts", "2"]) == 2
    assert "not both" in capsys.readouterr().err
