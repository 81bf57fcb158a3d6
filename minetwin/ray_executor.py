"""The Ray executor of ``cosim.batch``: a batch's tasks on a Ray cluster.

The cluster is started outside MineTwin with ``ray start`` (docs/scale-out.md);
the driver connects to it at ``address`` (``--address`` or the environment
variable ``MINETWIN_RAY_ADDRESS``). Each task needs one CPU
(``num_cpus = 1``: DEM runs are single-threaded) and is run again by Ray when
the worker running it dies, at most ``retries`` times (Ray's ``max_retries``;
an exception of the task itself is not retried, it is the task's record).
Inputs shared by every task go once into Ray's object store; the tasks' large
results go to their run folders, which every node must see at the same path
(one machine, or a shared file system). Ray is an optional extra
(``pip install minetwin[ray]``) imported only when this executor is made.
"""

from __future__ import annotations

import os

from cosim import batch
from cosim.errors import ValidationError

ADDRESS_VARIABLE = "MINETWIN_RAY_ADDRESS"


def _ray():
    try:
        import ray
    except ImportError:
        raise ValidationError("--executor", "local unless Ray is installed "
                              "(pip install 'minetwin[ray]')") from None
    return ray


class RayExecutor(batch.Executor):
    """Tasks on the Ray cluster at ``address``; ``workers`` (default: the
    cluster's CPUs) tasks submitted at once."""

    name = "ray"
    retries_on_its_own = True

    def __init__(self, address: str | None = None, workers: int | None = None,
                 retries: int = batch.RETRIES):
        ray = _ray()
        self.address = address or os.environ.get(ADDRESS_VARIABLE)
        if not self.address:
            raise ValidationError("--address", f"host:port of a Ray cluster's head (or set "
                                  f"{ADDRESS_VARIABLE}) with --executor ray")
        if not ray.is_initialized():
            try:
                # the workers' output stays in the nodes' session logs: one progress display
                ray.init(address=self.address, log_to_driver=False, configure_logging=False)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise ValidationError("--address", "the address of a running Ray cluster's "
                                      "head (ray start --head)",
                                      f"{self.address}: {exc}") from None
        if workers is None:
            workers = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        super().__init__(workers, retries)
        self._remote = ray.remote(num_cpus=1, max_retries=self.retries)(batch.call)
        self._common_ref = None
        self._open: set = set()

    def share(self, common):
        super().share(common)
        self._common_ref = None if common is None else _ray().put(common)

    def submit(self, function, kwargs):
        handle = self._remote.remote(function, kwargs, self._common_ref)
        self._open.add(handle)
        return handle

    def wait(self, handles, timeout):
        ray = _ray()
        if not ray.wait(handles, num_returns=1, timeout=timeout)[0]:
            return []
        return ray.wait(handles, num_returns=len(handles), timeout=0)[0]

    def outcome(self, handle):
        ray = _ray()
        self._open.discard(handle)
        try:
            return ray.get(handle)
        except ray.exceptions.RayTaskError as exc:
            if isinstance(exc.cause, batch.TaskFailed):
                raise batch.TaskFailed(str(exc.cause)) from None
            raise batch.TaskFailed(f"{type(exc.cause).__name__}: {exc.cause}") from None
        except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                ray.exceptions.ObjectLostError, ray.exceptions.OwnerDiedError) as exc:
            raise batch.WorkerLost(f"{type(exc).__name__} after {self.retries} retries") from None

    def close(self):
        ray = _ray()
        for handle in self._open:  # an interrupted batch: stop its tasks on the cluster
            ray.cancel(handle, force=True)
        self._open.clear()
