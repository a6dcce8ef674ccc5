"""Evaluation of large cohorts on a Dask cluster.

:func:`itk_nrreval.evaluate` with an ``Execution(scheduler=...)`` maps the tasks of
:mod:`itk_nrreval._pipeline` -- the same functions the in-process executor runs -- onto a
Dask cluster: per-image work and voxel-block sums become tasks, and no process holds all
the images. The per-image cache folder must be visible to the driver and every worker (a
shared filesystem on a cluster). The numbers equal the in-process run's (the driver adds
the blocks' sums in block order, whatever order they finish in).

The cluster is a local one (``"local"``), one already running (its address), or workers in
jobs of a batch system (``"slurm"``, ``"pbs"``, ``"sge"``), submitted and cancelled by
Dask's own job-queue integration, `dask-jobqueue <https://jobqueue.dask.org>`_.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from ._errors import InputError, readable
from ._progress import progress_bar

__all__ = [
    "DaskExecutor",
    "JOB_QUEUES",
    "JobResources",
    "check_job_queue",
    "check_scheduler",
    "cluster_client",
    "job_queue_cluster",
    "job_queue_options",
]

#: The batch systems dask-jobqueue drives: ``--scheduler`` name -> (its cluster class in
#: ``dask_jobqueue``, the command that submits a job).
JOB_QUEUES = {
    "slurm": ("SLURMCluster", "sbatch"),
    "pbs": ("PBSCluster", "qsub"),
    "sge": ("SGECluster", "qsub"),
}

#: A job's memory when neither the option nor Dask's jobqueue configuration gives it, per
#: core (each core runs one task, which holds one image's fields: about 1-2 GB at 1 mm).
DEFAULT_MEMORY_PER_CORE = "4GiB"

#: A walltime every one of the batch systems reads the same way (SLURM reads a bare number
#: as minutes, SGE as seconds: not accepted).
_WALLTIME = re.compile(r"\d+:[0-5]\d:[0-5]\d")


@dataclass(frozen=True, kw_only=True)
class JobResources:
    """What each worker job asks the batch system for (``None``: Dask's jobqueue config).

    Attributes
    ----------
    cores : int, optional
        Cores per job; the job runs one single-threaded worker per core (default: the
        config's ``cores``, else 1).
    memory : str, optional
        Memory per job, shared by its workers (``"8GiB"``; default: the config's
        ``memory``, else :data:`DEFAULT_MEMORY_PER_CORE` per core).
    walltime : str, optional
        ``HH:MM:SS`` (default: the config's ``walltime``, ``00:30:00`` as dask-jobqueue
        ships it).
    queue : str, optional
        The partition (SLURM) or queue (PBS, SGE).
    directives : tuple of str
        Further header lines, each without its prefix (``"--account=lab"`` becomes
        ``#SBATCH --account=lab``); they replace the config's ``job-extra-directives``.
    """

    cores: int | None = None
    memory: str | None = None
    walltime: str | None = None
    queue: str | None = None
    directives: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.cores is not None and (
            isinstance(self.cores, bool) or not isinstance(self.cores, int) or self.cores < 1
        ):
            raise ValueError(f"job_cores: expected a positive integer, got {readable(self.cores)}")
        if self.memory is not None:
            memory_bytes(self.memory, name="job_memory")
        if self.walltime is not None:
            check_walltime(self.walltime, name="job_walltime")
        if self.queue is not None and (not isinstance(self.queue, str) or not self.queue.strip()):
            raise ValueError(f"job_queue: expected a queue's name, got {readable(self.queue)}")
        if not isinstance(self.directives, (list, tuple)) or not all(
            isinstance(d, str) and d.strip() for d in self.directives
        ):
            raise ValueError(
                "job_directives: expected a sequence of header lines (strings), got "
                f"{readable(self.directives)}"
            )
        object.__setattr__(self, "directives", tuple(self.directives))


def memory_bytes(text: str, *, name: str = "job_memory") -> int:
    """`text` (``"8GiB"``, ``"16 GB"``) in bytes, as dask-jobqueue reads it; ValueError if
    it is not an amount of memory."""
    from dask.utils import parse_bytes

    try:
        value = parse_bytes(text) if isinstance(text, str) else None
    except ValueError:
        value = None
    if value is None or value <= 0:
        raise ValueError(
            f"{name}: expected an amount of memory like 8GiB or 16GB, got {readable(text)}"
        )
    return int(value)


def check_walltime(text: str, *, name: str = "job_walltime") -> str:
    """`text` if it is a walltime ``HH:MM:SS`` (hours may exceed 24), else ValueError."""
    if not isinstance(text, str) or not _WALLTIME.fullmatch(text):
        raise ValueError(
            f"{name}: expected a walltime HH:MM:SS like 02:00:00, got {readable(text)}"
        )
    return text


# ----------------------------------------------------------------------------- the cluster


@contextlib.contextmanager
def cluster_client(
    scheduler: str,
    *,
    workers: int | None = None,
    cache: str | os.PathLike | None = None,
    job: JobResources | None = None,
) -> Iterator:
    """A ``dask.distributed.Client``: a new local cluster, workers in batch jobs, or a
    cluster already running.

    Parameters
    ----------
    scheduler : str
        ``"local"`` starts a ``LocalCluster`` of `workers` processes with one thread each
        (closed on exit); ``"slurm"``, ``"pbs"`` or ``"sge"`` submits jobs of `job`'s
        resources running `workers` single-threaded workers in all, through dask-jobqueue
        (cancelled on exit); anything else is a scheduler address (``tcp://host:8786``) of a
        running cluster (Kubernetes, ``dask scheduler``...).
    workers : int, optional
        Local: the number of worker processes (default: the CPU count). Job queue: the
        number of workers (required), in ``ceil(workers / cores)`` jobs. Address: wait until
        that many workers have joined.
    cache : path, optional
        With a job queue (required): the per-image cache folder, checked before any job is
        submitted (:func:`check_job_queue`).
    job : JobResources, optional
        With a job queue: what each job asks for.

    Raises
    ------
    InputError
        An unknown scheduler, dask-jobqueue or the batch system's command missing, a cache
        folder that cannot be made or written, a job the batch system refuses, an address
        that does not answer.
    """
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - the dask extra is part of [all]
        raise InputError(
            "scheduler: dask.distributed is not installed (pip install 'itk-nrreval[dask]')"
        ) from exc
    check_scheduler(scheduler, workers)
    if scheduler in JOB_QUEUES:
        if workers is None or cache is None:
            raise ValueError(f"scheduler {scheduler!r}: workers and cache are required")
        check_job_queue(scheduler, cache=cache)
        options = job_queue_options(scheduler, job=job)
        with contextlib.closing(_cluster_class(scheduler)(**options)) as cluster:
            _submit(cluster, scheduler, jobs=math.ceil(workers / options["processes"]))
            with Client(cluster) as client:
                # Work starts with the first worker; the others join as the batch system
                # starts their jobs (Dask gives them tasks then), rather than idling the first
                # jobs' allocation until the last one leaves the queue.
                client.wait_for_workers(1)
                yield client
        return
    if scheduler == "local":
        cluster = LocalCluster(
            n_workers=workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )
        try:
            with Client(cluster) as client:
                yield client
        finally:
            cluster.close()
        return
    try:
        client = Client(scheduler, timeout="30s")
    except OSError as exc:
        raise InputError(f"scheduler: cannot connect to {scheduler!r} ({exc})") from exc
    try:
        if workers:
            client.wait_for_workers(workers)
        yield client
    finally:
        client.close()


def check_scheduler(scheduler: str, workers: int | None) -> None:
    """Raise InputError for a scheduler that is neither "local", a job queue ("slurm",
    "pbs", "sge") nor an address; ValueError for a worker count that is not positive."""
    host, _, port = str(scheduler).rpartition(":")
    if (
        scheduler != "local"
        and scheduler not in JOB_QUEUES
        and "://" not in scheduler
        and not (host and port.isdigit())
    ):
        raise InputError(
            f"scheduler: {scheduler!r} is neither 'local' nor an address like "
            f"tcp://host:8786, nor a job queue ({', '.join(JOB_QUEUES)})"
        )
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers: expected a positive integer, got {readable(workers)}")


def check_job_queue(scheduler: str, *, cache: str | os.PathLike, option: str = "cache") -> Path:
    """Refuse, before any job is submitted, what would make the jobs fail or wait forever.

    dask-jobqueue must be installed, the batch system's submit command (``sbatch``,
    ``qsub``) on the PATH, and the cache folder -- which every job reads and writes --
    writable, or creatable where it does not exist yet: a folder is made there (or in its
    nearest existing parent) and removed. Whether the jobs' nodes see the same folder cannot
    be checked from here (docs/large-cohorts.md).

    Parameters
    ----------
    scheduler : str
        ``"slurm"``, ``"pbs"`` or ``"sge"``.
    cache : path
        The per-image cache folder.
    option : str
        The cache's name in messages (``"--cache"`` on the command line).

    Returns
    -------
    Path
        The cache folder, absolute.

    Raises
    ------
    InputError
        One line naming what is missing.
    """
    class_name, command = JOB_QUEUES[scheduler]
    try:
        import dask_jobqueue  # noqa: F401
    except ImportError as exc:
        raise InputError(
            f"scheduler {scheduler}: dask-jobqueue is not installed "
            "(pip install 'itk-nrreval[dask]')"
        ) from exc
    if shutil.which(command) is None:
        raise InputError(
            f"scheduler {scheduler}: {command!r} not found on the PATH; run nrreval where "
            f"{scheduler.upper()} jobs are submitted (a login node)"
        )
    folder = Path(cache).absolute()
    existing = folder
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{option} {cache}: {existing} is a file, not a folder")
    try:
        # A folder made and removed where the cache is, or would be made: the cache makes
        # its own, and os.access can say yes where that fails (NFS root squash, a read-only
        # mount, /proc). Nothing is left: a cache made here inside --out, before the run
        # stages --out, would make --out a folder nrreval did not make.
        with tempfile.TemporaryDirectory(dir=existing, prefix=".nrreval-write-check-"):
            pass
    except OSError as exc:
        raise InputError(
            f"{option} {cache}: cannot be made or written ({exc.strerror or exc}); with "
            f"scheduler {scheduler} it must be a writable folder every job sees"
        ) from exc
    return folder


def job_queue_cluster(scheduler: str, *, job: JobResources | None = None):
    """A dask-jobqueue cluster (``SLURMCluster``, ``PBSCluster``, ``SGECluster``) for `job`,
    with no job submitted yet; its ``job_script()`` is what each job runs. Close it."""
    return _cluster_class(scheduler)(**job_queue_options(scheduler, job=job))


def job_queue_options(scheduler: str, *, job: JobResources | None = None) -> dict[str, Any]:
    """The keyword arguments of the dask-jobqueue cluster for `job`.

    Each job runs one single-threaded worker per core (``processes=cores``), as the local
    cluster does: a task sets SimpleITK's and numba's process-wide thread counts to one
    while it runs, which two tasks in one process would overwrite for each other. What
    `job` leaves out comes from Dask's jobqueue configuration (``jobqueue.<scheduler>.*``
    in ``~/.config/dask/jobqueue.yaml`` or ``DASK_JOBQUEUE__...`` variables), then from
    the defaults of :class:`JobResources`.
    """
    import dask

    job = job or JobResources()
    config = f"jobqueue.{scheduler}"
    cores = job.cores or dask.config.get(f"{config}.cores", None) or 1
    memory = job.memory or dask.config.get(f"{config}.memory", None)
    if memory is None:
        memory = f"{cores * memory_bytes(DEFAULT_MEMORY_PER_CORE) // 2**20}MiB"
    options: dict[str, Any] = dict(cores=cores, processes=cores, memory=memory)
    if job.walltime is not None:
        options["walltime"] = job.walltime
    if job.queue is not None:
        options["queue"] = job.queue
    if job.directives:
        options["job_extra_directives"] = list(job.directives)
    if dask.config.get(f"{config}.name", None) == "dask-worker":  # dask-jobqueue's default
        options["job_name"] = "nrreval"  # what squeue / qstat show
    # the dashboard on a free port, not 8787, which another cluster may hold (unless the
    # configuration names one)
    scheduler_options = dict(dask.config.get(f"{config}.scheduler-options", None) or {})
    scheduler_options.setdefault("dashboard_address", ":0")
    options["scheduler_options"] = scheduler_options
    return options


def _cluster_class(scheduler: str):
    import dask_jobqueue

    return getattr(dask_jobqueue, JOB_QUEUES[scheduler][0])


def _submit(cluster, scheduler: str, *, jobs: int) -> None:
    """Submit `jobs` worker jobs, and raise InputError if the batch system refuses one (a
    partition that does not exist, more memory than a node has...).

    The cluster's ``scale`` only schedules the submission (``SpecCluster._correct_state``)
    on its event loop, where a refusal is logged while the driver would wait for workers
    forever. Here the jobs are added to the cluster's ``worker_spec`` as ``scale`` adds
    them, and the same correction is awaited -- as dask.distributed's ``SpecCluster`` does
    on its own start -- so that a refusal is raised; then every job is taken back out
    (``scale(0)``, awaited: the jobs already accepted are cancelled), so that the cluster
    closes cleanly.
    """

    async def submit() -> None:
        while len(cluster.worker_spec) < jobs:
            cluster.worker_spec.update(cluster.new_worker_spec())
        try:
            await cluster._correct_state()
        except BaseException:
            from distributed.core import Status

            for job in cluster.workers.values():
                if job.job_id is None:  # not submitted: the cluster's close expects it so
                    job.status = Status.failed
            cluster.worker_spec.clear()
            await cluster._correct_state()
            raise

    try:
        cluster.sync(submit)
    except RuntimeError as exc:
        # dask-jobqueue's message: the command, its exit code, stdout and stderr; the
        # batch system's own lines say why ("sbatch: error: invalid partition specified")
        command = JOB_QUEUES[scheduler][1]
        text = str(exc)
        lines = (text.partition("stderr:")[2] or text).splitlines()
        said = [line.strip().removeprefix(f"{command}: error: ") for line in lines]
        raise InputError(
            f"scheduler {scheduler}: {command} refused the worker job: "
            + "; ".join(line for line in said if line)
        ) from exc


class DaskExecutor:
    """Run each task on a Dask cluster (see :class:`itk_nrreval._executors.Executor`).

    Parameters
    ----------
    client : dask.distributed.Client
        From :func:`cluster_client`.

    Attributes
    ----------
    n_workers : int
        The most workers the cluster had at the start or at the end of a :meth:`map`
        (workers in batch jobs join as their jobs start).
    """

    def __init__(self, client):
        self.client = client
        self.n_workers = self._workers_now()

    def _workers_now(self) -> int:
        return len(self.client.scheduler_info()["workers"])

    def map(
        self, fn: Callable, calls: Sequence[tuple], *, desc: str, progress: bool
    ) -> Iterator[tuple[int, Any]]:
        from dask.distributed import as_completed

        futures = [self.client.submit(_one_core, fn, *args, pure=False) for args in calls]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in progress_bar(
            as_completed(futures), desc=desc, total=len(futures), enabled=progress
        ):
            yield index[fut.key], fut.result()
            fut.release()  # the driver keeps only what it has read
        self.n_workers = max(self.n_workers, self._workers_now())


def _one_core(fn: Callable, *args):
    """Run `fn` on one core (a worker runs as many tasks at once as it has threads).

    SimpleITK's and numba's thread counts are restored afterwards: they are process-wide.
    """
    import numba

    sitk_threads = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    numba_threads = numba.get_num_threads()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    numba.set_num_threads(1)
    try:
        return fn(*args)
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(sitk_threads)
        numba.set_num_threads(numba_threads)
