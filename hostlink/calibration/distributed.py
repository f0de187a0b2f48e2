"""Calibration passes on a Dask cluster (https://distributed.dask.org): the per-chunk normal equations of the
bundle adjustment, and whole per-sensor runs of a fleet, mapped over workers by an established engine.

A pass (:func:`hostlink.calibration.bundle.chunk_pass`) is a pure function of one chunk of frames and a small
request (the camera, the robust scale, the rejected rows); its result is a sum over the chunk's frames
(:class:`hostlink.calibration.bundle.PassSums`). :class:`DaskPasses` submits one task per chunk and adds the results
in chunk order, so the camera is the one a single process finds, to the rounding of the additions.

Chunks on disk (the spool of :func:`hostlink.calibration.run.calibrate_archive`) travel as file names: every worker
must see the spool directory (a LocalCluster does; a remote cluster needs it on shared storage). Chunks in memory
are scattered to the workers once and stay there for every pass.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from hostlink.calibration.passes import PassRequest, PassSums, chunk_pass, empty_pass
from hostlink.calibration.source import ChunkSource
from hostlink.errors import UserError, install_hint

#: Workers of the local cluster of ``--dask local`` unless told (one process each, one thread: numpy's own threads
#: do the rest).
DEFAULT_WORKERS = 2
#: Seconds to wait for a remote scheduler to answer before giving up with a one-line error.
CONNECT_TIMEOUT_S = 30


@contextmanager
def dask_client(
    address: str, n_workers: int = DEFAULT_WORKERS, processes: bool = True, timeout_s: float = CONNECT_TIMEOUT_S
) -> Iterator[object]:
    """A ``distributed.Client``: on a new LocalCluster of ``n_workers`` workers when ``address`` is ``"local"``,
    else connected to the scheduler at ``address`` (e.g. ``tcp://host:8786``, waiting at most ``timeout_s``). Closed
    on exit. A missing package or
    an unreachable scheduler is a one-line :class:`UserError`."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UserError(f"--dask needs Dask: {install_hint('dask')}") from None
    cluster = None
    try:
        if address == "local":
            cluster = LocalCluster(
                # the scheduler's HTTP endpoint on a free port: never a clash with another cluster on the machine
                n_workers=n_workers,
                threads_per_worker=1,
                processes=processes,
                dashboard_address=":0",
            )
            client = Client(cluster)
        else:
            client = Client(address, timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:
        if cluster is not None:
            cluster.close()
        raise UserError(f"--dask {address}: cannot reach the Dask scheduler ({exc})") from None
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _pass_on_worker(handle: object, load: Callable | None, req: PassRequest) -> PassSums:
    return chunk_pass(handle if load is None else load(handle), req)


class DaskPasses:
    """A pass runner (:data:`hostlink.calibration.bundle.PassRunner`) on a Dask client: one task per chunk,
    results added in chunk order."""

    def __init__(self, client: object) -> None:
        self.client = client
        self._placed: dict[int, tuple[ChunkSource, list]] = {}

    def _handles(self, source: ChunkSource) -> list:
        key = id(source)
        if key not in self._placed:
            handles = list(source.handles)
            if source.load is None:  # data in memory: moved to the workers once, kept for every pass
                handles = self.client.scatter(handles)
            self._placed[key] = (source, handles)
        return self._placed[key][1]

    def __call__(self, source: ChunkSource, req: PassRequest) -> PassSums:
        handles = self._handles(source)
        req_future = self.client.scatter(req, broadcast=True, hash=False)
        futures = [self.client.submit(_pass_on_worker, h, source.load, req_future, pure=False) for h in handles]
        out = empty_pass(req.cols.size, req.final)
        for f in futures:
            out = out.merge(f.result())
            f.release()
        return out


def map_sensors(function: Callable, jobs: Sequence[tuple], client: object) -> list:
    """``[function(*job) for job in jobs]`` with each job (one sensor's whole run) a task on the cluster, results
    in job order: a fleet's sensors calibrated side by side. ``function`` and its arguments must be picklable."""
    futures = [client.submit(function, *job, pure=False) for job in jobs]
    return [f.result() for f in futures]
