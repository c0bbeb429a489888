"""The worker pool of the Ape-X actors and of DAgger's labelling workers: `num_workers` copies of
a worker class, as Ray actors (a local Ray on `num_cpus` CPUs by default, so traffic stays on this
machine, or the cluster at `address`) or in this process (tests, debugging, `use_ray: false`).

    pool = make_pool(Worker, [args_0, args_1], use_ray=True, address=None, num_cpus=2)
    pool.broadcast(weights, version)      # each worker loads them before its next call
    for index in pool.idle():
        pool.submit(index, "method", job)
    for index, result in pool.ready(block=True): ...
    for result in pool.map("method", jobs): ...   # results as they finish
    pool.close()

A worker class has `set_weights(state_dict, version)`. Ray actors run their calls in the
background (`in_background`); the in-process pool runs one call at a time, when its result is
asked for, on the workers in turn."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from typing import Any


def init_ray(address: str | None, num_cpus: int) -> bool:
    """Start (or join) Ray unless it runs already; True when this call started it."""
    import ray

    if ray.is_initialized():
        return False
    kwargs = dict(include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False,
                  configure_logging=True)
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray.init(num_cpus=num_cpus, **kwargs)
    return True


def actor_cpus(address: str | None, num_cpus: int, num_actors: int) -> float:
    """CPUs per actor: locally the actors share the configured CPUs; on a cluster, one each."""
    return 1.0 if address else min(1.0, num_cpus / num_actors)


class CpuMeter:
    """CPU time a run really used (for the cards' compute): the driver process (every thread)
    plus every worker process, which reports its own cumulative process time with each result
    (`pid`, `process_cpu_seconds`). Wall time x reserved CPUs overstates it when runs share a
    machine. Not counted: Ray's own daemons (raylet, GCS)."""

    def __init__(self):
        self.driver_start = time.process_time()
        self.actor_seconds = 0.0
        self._last: dict[int, float] = {}  # worker pid -> cumulative seconds already counted

    def actor_report(self, result: dict) -> None:
        pid, cumulative = result.get("pid"), result.get("process_cpu_seconds")
        if pid is None or cumulative is None or pid == os.getpid():
            return  # in-process workers are in the driver's own time
        self.actor_seconds += max(0.0, float(cumulative) - self._last.get(pid, 0.0))
        self._last[pid] = float(cumulative)

    def seconds(self) -> float:
        return time.process_time() - self.driver_start + self.actor_seconds


class _Pool:
    """What both pools share: the latest weights, and which worker holds which version."""

    in_background = False

    def __init__(self, size: int):
        self.weights: tuple[Any, Any] | None = None  # (weights or their Ray reference, version)
        self.versions: list[Any] = [object()] * size  # no version yet
        self.pending: dict | list = {}  # the calls in flight (and their worker)

    def idle(self) -> list[int]:
        raise NotImplementedError

    def map(self, method: str, jobs: list) -> Iterator[Any]:
        """Run `method(job)` for every job on the idle workers; yield the results as they finish."""
        queue = list(jobs)
        while queue or self.pending:
            for index in self.idle():
                if not queue:
                    break
                self.submit(index, method, queue.pop(0))
            for _, result in self.ready(block=True):
                yield result


class LocalPool(_Pool):
    def __init__(self, worker_cls, worker_args: list[tuple]):
        super().__init__(len(worker_args))
        self.workers = [worker_cls(*args) for args in worker_args]
        self.cursor = 0  # the worker whose turn it is
        self.pending: list = []  # (worker index, method, args) not run yet

    def broadcast(self, weights: dict, version) -> None:
        self.weights = (weights, version)

    def idle(self) -> list[int]:
        return [] if self.pending else [self.cursor]

    def submit(self, index: int, method: str, *args) -> None:
        self.pending.append((index, method, args))
        self.cursor = (index + 1) % len(self.workers)

    def ready(self, block: bool) -> list[tuple[int, Any]]:
        """The pending call, run now (an in-process call is always ready)."""
        results = []
        while self.pending:
            index, method, args = self.pending.pop(0)
            worker = self.workers[index]
            if self.weights is not None and self.versions[index] != self.weights[1]:
                worker.set_weights(*self.weights)
                self.versions[index] = self.weights[1]
            results.append((index, getattr(worker, method)(*args)))
        return results

    def close(self) -> None:
        self.pending.clear()


class RayPool(_Pool):
    in_background = True

    def __init__(self, worker_cls, worker_args: list[tuple], address: str | None,
                 num_cpus: int):
        import ray

        super().__init__(len(worker_args))
        self.ray = ray
        self.started = init_ray(address, num_cpus)
        cpus = actor_cpus(address, num_cpus, len(worker_args))
        remote_cls = ray.remote(num_cpus=cpus)(worker_cls)
        self.actors = [remote_cls.remote(*args) for args in worker_args]

    def broadcast(self, weights: dict, version) -> None:
        self.weights = (self.ray.put(weights), version)

    def idle(self) -> list[int]:
        busy = set(self.pending.values())
        return [i for i in range(len(self.actors)) if i not in busy]

    def submit(self, index: int, method: str, *args) -> None:
        actor = self.actors[index]
        if self.weights is not None and self.versions[index] != self.weights[1]:
            actor.set_weights.remote(*self.weights)  # an actor runs its calls in order
            self.versions[index] = self.weights[1]
        self.pending[getattr(actor, method).remote(*args)] = index

    def ready(self, block: bool) -> list[tuple[int, Any]]:
        """Every finished call; with `block`, after waiting for the first one."""
        if not self.pending:
            return []
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=None if block else 0)
        if ready:  # take every finished one without waiting more
            more, _ = self.ray.wait([r for r in self.pending if r not in ready],
                                    num_returns=len(self.pending) - len(ready), timeout=0)
            ready = ready + more
        return [(self.pending.pop(ref), self.ray.get(ref)) for ref in ready]

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)
        self.pending.clear()
        if self.started:
            self.ray.shutdown()


def make_pool(worker_cls, worker_args: list[tuple], use_ray: bool, address: str | None = None,
              num_cpus: int = 1) -> LocalPool | RayPool:
    """One worker per entry of `worker_args` (its constructor's arguments)."""
    if use_ray:
        return RayPool(worker_cls, worker_args, address, num_cpus)
    return LocalPool(worker_cls, worker_args)
