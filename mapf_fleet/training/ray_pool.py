"""Ray for the trainer's actors and DAgger's labelling workers: a local Ray on `num_cpus` CPUs
by default (traffic stays on this machine), or the cluster at `address`."""

from __future__ import annotations

import logging


def init_ray(address: str, num_cpus: int) -> bool:
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


def actor_cpus(address: str, num_cpus: int, num_actors: int) -> float:
    """CPUs per actor: locally the actors share the configured CPUs; on a cluster, one each."""
    return 1.0 if address else min(1.0, num_cpus / num_actors)
