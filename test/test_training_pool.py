"""The worker pool the Ape-X actors and DAgger share (training/ray_pool.py), in-process: the
workers take turns, load the latest weights before their next call, and `map` returns every
job's result."""

import pytest

from mapf_fleet.training.ray_pool import CpuMeter, LocalPool, make_pool


class Echo:
    def __init__(self, name):
        self.name, self.weights, self.loads = name, None, 0

    def set_weights(self, weights, version):
        self.weights, self.loads = (weights, version), self.loads + 1

    def work(self, job):
        return {"worker": self.name, "job": job, "weights": self.weights}


def test_in_process_workers_take_turns_with_the_latest_weights():
    pool = make_pool(Echo, [("a",), ("b",)], use_ray=False)
    assert isinstance(pool, LocalPool) and not pool.in_background
    pool.broadcast({"w": 1}, 1)
    results = list(pool.map("work", [10, 11, 12]))
    assert [(r["worker"], r["job"]) for r in results] == [("a", 10), ("b", 11), ("a", 12)]
    assert all(r["weights"] == ({"w": 1}, 1) for r in results)
    assert [w.loads for w in pool.workers] == [1, 1]  # loaded once per version, not per call
    pool.broadcast({"w": 2}, 2)
    # one call in flight at a time: the idle worker is the next in turn
    assert pool.idle() == [1]
    pool.submit(1, "work", 13)
    assert pool.idle() == []
    [(index, result)] = pool.ready(block=False)
    assert index == 1 and result["weights"] == ({"w": 2}, 2)
    assert pool.ready(block=True) == [] and pool.idle() == [0]
    pool.close()


def test_cpu_meter_counts_each_worker_process_once():
    meter = CpuMeter()
    meter.actor_report({"pid": -5, "process_cpu_seconds": 2.0})
    meter.actor_report({"pid": -5, "process_cpu_seconds": 3.5})
    meter.actor_report({"pid": -6, "process_cpu_seconds": 1.0})
    assert meter.actor_seconds == pytest.approx(4.5)
