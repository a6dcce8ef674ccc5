"""Cohorts on a batch system through dask-jobqueue (issue 46, item 3).

``nrreval evaluate --scheduler slurm|pbs|sge`` submits worker jobs through dask-jobqueue.
Against a real single-node SLURM (Debian's slurm-wlm and munge, which ``make test`` installs
as root, started on localhost by the session fixture ``slurm_conf``): results.json equals
the in-process one number for number, and a job the batch system refuses is one line. Where
SLURM cannot be installed or started those tests are skipped with the reason, and the rest
still run without a batch system: the job script dask-jobqueue writes for the options
(SLURM, PBS and SGE), and what is refused before any job is submitted.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from test_dask_parity import assert_same_json, population, results_json

import itk_nrreval as nr
from itk_nrreval import _scaleout
from itk_nrreval._errors import InputError
from itk_nrreval.cli import main

pytest.importorskip("dask_jobqueue")

#: What the single-node SLURM needs (packages munge, slurmctld, slurmd, slurm-client).
SLURM_PROGRAMS = ("munged", "slurmctld", "slurmd", "sinfo", "sbatch", "squeue")
STARTUP_S = 60  # munged's socket, then the node idle in sinfo


# ----------------------------------------------------------------------------- a real SLURM


def _free_ports(n: int) -> list[int]:
    """`n` distinct ports free now (all held open at once, so none is given twice)."""
    sockets = [socket.socket() for _ in range(n)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return f"{path.name}: none"
    return f"{path.name}: " + " | ".join(text[-lines:])


def _hardware() -> str:
    """This machine as slurmd sees it (``CPUs=2 ... RealMemory=24105``): a node declared
    with more than it has would be drained instead of idle."""
    done = subprocess.run(["slurmd", "-C"], capture_output=True, text=True, timeout=30)
    first = done.stdout.splitlines()[0] if done.returncode == 0 and done.stdout else ""
    fields = [f for f in first.split() if not f.startswith(("NodeName=", "UpTime="))]
    if not any(f.startswith("CPUs=") for f in fields):
        pytest.skip(f"SLURM: slurmd -C did not describe this machine ({done.stderr.strip()})")
    return " ".join(fields)


def _write_config(folder: Path) -> Path:
    """A minimal slurm.conf: one node (this machine, as localhost) in one partition; no
    cgroups (containers often lack them), no accounting; state, logs and ports its own."""
    for sub in ("state", "spool", "log"):
        (folder / sub).mkdir()
    conf = folder / "slurm.conf"
    slurmctld_port, slurmd_port = _free_ports(2)
    conf.write_text(
        f"""\
ClusterName=nrreval-test
SlurmctldHost=localhost
SlurmctldPort={slurmctld_port}
SlurmdPort={slurmd_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={folder}/munge.socket
StateSaveLocation={folder}/state
SlurmdSpoolDir={folder}/spool
SlurmctldPidFile={folder}/slurmctld.pid
SlurmdPidFile={folder}/slurmd.pid
SlurmctldLogFile={folder}/log/slurmctld.log
SlurmdLogFile={folder}/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
NodeName=localhost NodeAddr=127.0.0.1 {_hardware()} State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
"""
    )
    return conf


@pytest.fixture(scope="session")
def slurm_conf():
    """A single-node SLURM on localhost for this session: munged, slurmctld and slurmd
    started as root in the foreground (their processes are this fixture's to stop), with
    their own key, socket, ports and state in a temporary folder. Yields its slurm.conf;
    skips, saying what failed, where they are not installed or do not start."""
    missing = [p for p in SLURM_PROGRAMS if shutil.which(p) is None]
    if missing:
        pytest.skip(
            f"SLURM not installed ({', '.join(missing)} not found; `make test` installs "
            "slurm-wlm and munge where it runs as root with apt-get)"
        )
    if os.geteuid() != 0:
        pytest.skip("SLURM: starting slurmctld and slurmd on localhost takes root")
    # short: munged's socket path must fit a Unix socket's 108 bytes
    folder = Path(tempfile.mkdtemp(prefix="nrreval-slurm-"))
    daemons: list[subprocess.Popen] = []

    def start(*command: str) -> None:
        out = open(folder / f"{Path(command[0]).name}.out", "wb")  # the daemon keeps it open
        daemons.append(subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT))
        out.close()

    def failed(what: str) -> str:
        """What failed, with the last lines the daemon that exited (else every one) wrote."""
        exited = [d for d in daemons if d.poll() is not None][:1]
        if exited:
            what = f"{Path(exited[0].args[0]).name} exited with code {exited[0].returncode}"
        names = [Path(d.args[0]).name for d in exited or daemons]
        logs = [folder / f"{n}.out" for n in names] + [folder / f"log/{n}.log" for n in names]
        said = "; ".join(_tail(p) for p in logs if p.exists() and p.stat().st_size)
        return f"SLURM: {what}" + (f" ({said})" if said else "")

    try:
        conf = _write_config(folder)
        key = folder / "munge.key"
        key.write_bytes(os.urandom(128))
        key.chmod(0o600)
        start(
            "munged",
            "--foreground",
            "--force",
            f"--socket={folder}/munge.socket",
            f"--key-file={key}",
            f"--log-file={folder}/munged.log",
            f"--pid-file={folder}/munged.pid",
            f"--seed-file={folder}/munged.seed",
        )
        deadline = time.monotonic() + STARTUP_S
        while not (folder / "munge.socket").exists():
            if daemons[0].poll() is not None or time.monotonic() > deadline:
                pytest.skip(failed("munged did not start"))
            time.sleep(0.1)
        start("slurmctld", "-D", "-f", str(conf))
        start("slurmd", "-D", "-f", str(conf), "-N", "localhost")
        env = {**os.environ, "SLURM_CONF": str(conf)}
        state = ""
        while state != "idle":
            if any(d.poll() is not None for d in daemons) or time.monotonic() > deadline:
                pytest.skip(failed(f"the node is not idle in sinfo ({state or 'no answer'})"))
            time.sleep(0.2)
            state = subprocess.run(
                ["sinfo", "-h", "-n", "localhost", "-o", "%T"],
                capture_output=True,
                text=True,
                env=env,
                timeout=30,
            ).stdout.strip()
        yield conf
    finally:
        for daemon in reversed(daemons):
            daemon.terminate()
            try:
                daemon.wait(timeout=15)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
        shutil.rmtree(folder, ignore_errors=True)


def _jobs(conf: Path) -> list[str]:
    """The jobs SLURM still knows as pending or running (a cancelled job leaves at once or
    after its completing state: waited for, up to 30 s)."""
    env = {**os.environ, "SLURM_CONF": str(conf)}
    deadline = time.monotonic() + 30
    while True:
        listed = subprocess.run(
            ["squeue", "-h", "-o", "%i %T"], capture_output=True, text=True, env=env, timeout=30
        ).stdout.split("\n")
        jobs = [line for line in listed if line.strip()]
        if not jobs or time.monotonic() > deadline:
            return jobs
        time.sleep(0.2)


COMMON = ["--samples", "2000", "--seed", "5", "--no-figures", "--quiet"]


def test_slurm_results_json_equals_in_process(slurm_conf, tmp_path, monkeypatch, capsys):
    """The parity case of test_dask_parity (N = 4, 96 x 96, a displacement field each)
    through ``--scheduler slurm``: two workers in two one-core jobs of the real SLURM. Its
    results.json equals the in-process one key by key, floats to 1e-9 relative (in practice
    to the last digit); only how it ran differs (``run``: scheduler, workers, threads)."""
    manifest = population(tmp_path)
    monkeypatch.setenv("SLURM_CONF", str(slurm_conf))
    monkeypatch.chdir(tmp_path)  # where the jobs' slurm-<id>.out go
    assert main(["evaluate", str(manifest), "--out", str(tmp_path / "single"), *COMMON]) == 0
    args = [
        "evaluate",
        str(manifest),
        "--out",
        str(tmp_path / "slurm"),
        *COMMON,
        "--scheduler",
        "slurm",
        "--workers",
        "2",
        "--job-cores",
        "1",
        "--job-memory",
        "1GiB",
        "--job-walltime",
        "00:10:00",
        "--cache",
        str(tmp_path / "shared" / "cache"),
    ]
    assert main(args) == 0, capsys.readouterr().err
    single, on_slurm = results_json(tmp_path / "single"), results_json(tmp_path / "slurm")
    assert (single["run"]["scheduler"], on_slurm["run"]["scheduler"]) == (None, "slurm")
    assert on_slurm["run"]["threads"] == 1 and 1 <= on_slurm["run"]["workers"] <= 2
    assert on_slurm["run"]["cache_computed"] == single["run"]["cache_computed"] > 0
    assert_same_json(single, on_slurm)
    # the workers ran in SLURM jobs (their logs), which are gone at the end
    logs = sorted(tmp_path.glob("slurm-*.out"))
    assert logs and any("Registered to" in p.read_text() for p in logs), logs
    assert _jobs(slurm_conf) == []


def test_a_job_slurm_refuses_is_one_line(slurm_conf, tmp_path, monkeypatch, capsys):
    """sbatch's refusal (a partition that does not exist) ends the run at once with its
    words in one line, exit 2; no job is left."""
    manifest = population(tmp_path, size=32)
    monkeypatch.setenv("SLURM_CONF", str(slurm_conf))
    monkeypatch.chdir(tmp_path)
    code = main(
        ["evaluate", str(manifest), "--out", str(tmp_path / "out"), *COMMON]
        + ["--scheduler", "slurm", "--workers", "1", "--cache", str(tmp_path / "cache")]
        + ["--job-queue", "no-such-partition"]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert_one_line(err, "sbatch refused", "invalid partition", "no-such-partition")
    assert _jobs(slurm_conf) == []


# ----------------------------------------------------------------------------- no batch system


def assert_one_line(err: str, *fragments: str) -> None:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


@pytest.fixture
def fake_submit(tmp_path, monkeypatch):
    """``sbatch`` and ``qsub`` first on the PATH, which record being called and fail as a
    batch system that refuses the job does; returns the file of their calls."""
    folder = tmp_path / "fake-bin"
    folder.mkdir()
    calls = tmp_path / "submitted"
    for command in ("sbatch", "qsub"):
        script = folder / command
        script.write_text(
            f'#!/bin/sh\necho "{command} $*" >> "{calls}"\n'
            f'echo "{command}: error: invalid partition specified: nope" >&2\nexit 1\n'
        )
        script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ.get('PATH', '')}")
    return calls


#: What the job scripts must say for JOB_ARGS, per batch system: the header lines (in this
#: order) and the worker command's options (2 single-threaded workers sharing 6 GiB).
JOB_ARGS = [
    "--job-cores",
    "2",
    "--job-memory",
    "6GiB",
    "--job-walltime",
    "01:30:00",
    "--job-queue",
    "short",
]
EXPECTED_HEADERS = {
    "slurm": (
        ["--job-directive=--account=lab", "--job-directive=--constraint=avx2"],
        [
            "#SBATCH -J nrreval",
            "#SBATCH -p short",
            "#SBATCH -n 1",
            "#SBATCH --cpus-per-task=2",
            "#SBATCH --mem=6G",
            "#SBATCH -t 01:30:00",
            "#SBATCH --account=lab",
            "#SBATCH --constraint=avx2",
        ],
    ),
    "pbs": (
        ["--job-directive=-A lab", "--job-directive=-l place=scatter"],
        [
            "#PBS -N nrreval",
            "#PBS -q short",
            # dask-jobqueue writes PBS's binary units as PBS names them (MB = MiB)
            "#PBS -l select=1:ncpus=2:mem=6144MB",
            "#PBS -l walltime=01:30:00",
            "#PBS -A lab",
            "#PBS -l place=scatter",
        ],
    ),
    # SGE's cores and memory are site-named resources (a parallel environment, h_vmem or
    # mem_free): requested by directives; the workers are sized by --job-cores/--job-memory
    "sge": (
        ["--job-directive=-pe smp 2", "--job-directive=-l h_vmem=3G"],
        [
            "#$ -N nrreval",
            "#$ -q short",
            "#$ -l h_rt=01:30:00",
            "#$ -cwd",
            "#$ -j y",
            "#$ -pe smp 2",
            "#$ -l h_vmem=3G",
        ],
    ),
}


@pytest.mark.parametrize("scheduler", sorted(EXPECTED_HEADERS))
def test_job_script_carries_the_options(scheduler, tmp_path, fake_submit, monkeypatch, capsys):
    """The script dask-jobqueue writes for ``--scheduler X --job-*``, taken where the jobs
    would be submitted (through the CLI, the Execution and the cluster): its header lines
    for cores, memory, walltime, queue and each directive, and its worker command (one
    single-threaded worker per core, the job's memory shared)."""
    seen = {}

    def capture(cluster, scheduler, *, jobs):
        seen["script"], seen["jobs"] = cluster.job_script(), jobs
        raise InputError("captured")

    monkeypatch.setattr(_scaleout, "_submit", capture)
    manifest = population(tmp_path, size=32)
    directives, expected = EXPECTED_HEADERS[scheduler]
    code = main(
        ["evaluate", str(manifest), "--out", str(tmp_path / "out"), *COMMON]
        + ["--scheduler", scheduler, "--workers", "3", "--cache", str(tmp_path / "cache")]
        + JOB_ARGS
        + directives
    )
    assert code == 2 and "captured" in capsys.readouterr().err
    assert seen["jobs"] == 2  # 3 workers in jobs of 2
    lines = seen["script"].splitlines()
    prefix = expected[0].split()[0]
    assert [line for line in lines if line.startswith(prefix + " ")] == expected
    worker = next(line for line in lines if "distributed.cli.dask_worker" in line).split()
    options = dict(zip(worker, worker[1:], strict=False))
    assert (options["--nworkers"], options["--nthreads"]) == ("2", "1")
    assert options["--memory-limit"] == "3.00GiB"
    assert worker[0] == sys.executable
    assert not fake_submit.exists()  # nothing was submitted


def test_job_script_defaults(tmp_path):
    """Without options: one core and 4 GiB per job, dask-jobqueue's 30 minutes."""
    with _scaleout.job_queue_cluster("slurm") as cluster:
        header = [line for line in cluster.job_script().splitlines() if line.startswith("#SBATCH")]
    assert header == [
        "#SBATCH -J nrreval",
        "#SBATCH -n 1",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --mem=4G",
        "#SBATCH -t 00:30:00",
    ]


def test_a_refused_job_is_one_line_without_slurm(tmp_path, fake_submit, capsys):
    """The submit command's refusal (here a stand-in sbatch that says what sbatch says of
    an unknown partition) ends the run at once, its words in one line, exit 2. The cache
    inside --out, where the check before submitting leaves nothing (a cache folder made
    there would make --out a folder nrreval did not make)."""
    manifest = population(tmp_path, size=32)
    out = tmp_path / "out"
    code = main(
        ["evaluate", str(manifest), "--out", str(out), *COMMON]
        + ["--scheduler", "slurm", "--workers", "1", "--cache", str(out / "cache")]
    )
    assert code == 2
    assert_one_line(
        capsys.readouterr().err, "sbatch refused the worker job", "invalid partition specified"
    )
    assert fake_submit.read_text().startswith("sbatch ")


@pytest.mark.parametrize(
    "args, fragments",
    [
        (["--scheduler", "slurm", "--workers", "2"], ["--scheduler slurm needs --cache"]),
        (["--scheduler", "pbs", "--cache", "{tmp}/cache"], ["--scheduler pbs needs --workers"]),
        (["--scheduler", "local", "--job-memory", "4GiB"], ["--job-memory goes with"]),
        (["--job-directive=--account=lab"], ["--job-directive goes with"]),
        (["--scheduler", "slurms", "--workers", "1"], ["'slurms'", "slurm, pbs, sge"]),
        (["--scheduler", "slurm", "--job-memory", "lots"], ["--job-memory", "'lots'"]),
        (["--scheduler", "slurm", "--job-walltime", "90"], ["--job-walltime", "HH:MM:SS"]),
        (["--scheduler", "slurm", "--job-cores", "0"], ["--job-cores", "'0'"]),
        (["--scheduler", "slurm", "--job-directive="], ["--job-directive", "empty"]),
        (["--scheduler", "slurm", "--job-queue", " "], ["--job-queue", "empty"]),
        # /proc takes no folder, even from root (for whom os.access says yes)
        (
            ["--scheduler", "slurm", "--workers", "1", "--cache", "/proc/nrreval-cache"],
            ["--cache /proc/nrreval-cache", "not"],
        ),
        (
            ["--scheduler", "slurm", "--workers", "1", "--cache", "{tmp}/cache"],
            ["'sbatch' not found on the PATH"],
        ),
        (
            ["--scheduler", "sge", "--workers", "1", "--cache", "{tmp}/cache"],
            ["'qsub' not found on the PATH"],
        ),
    ],
)
def test_refused_before_any_job_is_submitted(
    args, fragments, tmp_path, fake_submit, monkeypatch, capsys
):
    """Each is one line naming the option, exit 2; nothing is submitted and no output
    folder is made."""
    manifest = population(tmp_path, size=32)
    if any("not found on the PATH" in f for f in fragments):
        monkeypatch.setenv("PATH", str(tmp_path / "empty-bin"))
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    code = main(["evaluate", str(manifest), "--out", str(tmp_path / "out"), *COMMON, *args])
    assert code == 2
    assert_one_line(capsys.readouterr().err, *fragments)
    assert not fake_submit.exists()
    assert not (tmp_path / "out").exists()


def test_execution_checks_its_job_options(tmp_path):
    """The library's Execution refuses what the CLI refuses, naming the attribute."""
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match="workers: required with scheduler='slurm'"):
        nr.Execution(scheduler="slurm", cache=cache)
    with pytest.raises(ValueError, match="cache: required with scheduler='sge'"):
        nr.Execution(scheduler="sge", workers=2)
    with pytest.raises(ValueError, match="job_.*only with a job-queue scheduler"):
        nr.Execution(scheduler="local", job_queue="short")
    for bad, match in [
        (dict(job_memory="lots"), "job_memory"),
        (dict(job_walltime="90"), "job_walltime"),
        (dict(job_cores=0), "job_cores"),
        (dict(job_directives="--account=lab"), "job_directives"),
        (dict(job_directives=5), "job_directives"),
    ]:
        with pytest.raises(ValueError, match=match):
            nr.Execution(scheduler="slurm", workers=1, cache=cache, **bad)
    execution = nr.Execution(
        scheduler="pbs", workers=4, cache=cache, job_cores=2, job_directives=["-A lab"]
    )
    assert execution.job_directives == ("-A lab",)  # a list is kept as a tuple (frozen)
