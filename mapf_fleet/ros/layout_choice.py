"""How `mapf-fleet up` lays out a fleet on this machine (plain Python, no rclpy): the process
layout chosen from the robot count and the memory available when `--nodes-per-process` is not
given, and the refusals of a layout or a generated map that would not fit in memory (one line
each, before anything starts: a fleet of a process per robot at 512 robots used to take all of
the machine's memory and leave it unresponsive; docs/results.md, "Process layouts")."""

from __future__ import annotations

from mapf_fleet.fleet.up_options import (MAX_NODES_PER_PROCESS, UpError, policy_processes,
                                         recommended_nodes_per_process)

# Memory of one policy process (Python, torch, rclpy, the model) and what each robot's nodes it
# hosts add, both set above what was measured (docs/results.md, "Process layouts") so that the
# estimate errs on the safe side, the simulator and `up` itself; the share of
# MemAvailable a fleet may take (the rest: the system, whatever else runs). docs/fleet.md,
# "Process layouts".
POLICY_PROCESS_MB = 300.0
POLICY_ROBOT_MB = 1.5
FLEET_BASE_MB = 700.0
MEMORY_SHARE = 0.8
# Bytes per cell of generating a random map (the uniform draws, the map, its regions' labels)
MAP_BYTES_PER_CELL = 24


def available_memory_mb(meminfo: str = "/proc/meminfo") -> float | None:
    """MemAvailable in MB (Linux), None when it cannot be read."""
    try:
        with open(meminfo) as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def fleet_memory_mb(num_robots: int, processes: int) -> float:
    """Estimated memory of a fleet whose policy nodes run in `processes` processes."""
    return FLEET_BASE_MB + processes * POLICY_PROCESS_MB + num_robots * POLICY_ROBOT_MB


def _budget_processes(num_robots: int, available_mb: float) -> int:
    """The most policy processes `available_mb` holds (MEMORY_SHARE of it) for this fleet."""
    budget = MEMORY_SHARE * available_mb - FLEET_BASE_MB - num_robots * POLICY_ROBOT_MB
    return int(budget // POLICY_PROCESS_MB)


def choose_layout(num_robots: int, available_mb: float | None,
                  recorder: bool = False) -> tuple[int, str]:
    """`--nodes-per-process` for `up` when none is given: the layout recommended for the robot
    count (`recommended_nodes_per_process`: a process per robot for small fleets, at most 8
    processes from 256 robots), with fewer, larger processes when the memory available
    (`available_mb`, None: unknown) does not hold that many. (K, the one line saying so: "" for
    the plain process per robot); UpError when not even processes of MAX_NODES_PER_PROCESS
    robots fit."""
    k = recommended_nodes_per_process(num_robots, recorder)
    why = "the robot count"
    if available_mb is not None:
        fit = _budget_processes(num_robots, available_mb)
        fewest = -(-num_robots // MAX_NODES_PER_PROCESS)
        if fit < fewest:
            raise UpError(
                f"{num_robots} robots need about {fleet_memory_mb(num_robots, fewest):,.0f} MB "
                f"(at least {fewest} policy process(es) of about {POLICY_PROCESS_MB:.0f} MB, "
                f"{MAX_NODES_PER_PROCESS} robots at most each), more than "
                f"{MEMORY_SHARE:.0%} of the {available_mb:,.0f} MB available: use fewer robots "
                f"or free memory")
        if policy_processes(num_robots, False, k) > fit:
            k = -(-num_robots // fit)
            why = f"the {available_mb / 1024:.1f} GiB of memory available"
    if k == 1:
        return 1, ""
    processes = policy_processes(num_robots, False, k)
    note = (f"{num_robots} robots in {processes} policy process(es) of up to {k} robots "
            f"(--nodes-per-process {k}, chosen for {why}; about "
            f"{fleet_memory_mb(num_robots, processes) / 1024:.1f} GiB)")
    return k, note


def layout_memory_problem(num_robots: int, single_process: bool, nodes_per_process: int,
                          available_mb: float | None) -> str:
    """Why the given layout is refused for memory ("" when it fits or memory is unknown): its
    estimate (`fleet_memory_mb`) is above MEMORY_SHARE of what is available."""
    if available_mb is None:
        return ""
    processes = policy_processes(num_robots, single_process, nodes_per_process)
    needed = fleet_memory_mb(num_robots, processes)
    if needed <= MEMORY_SHARE * available_mb:
        return ""
    fit = max(1, _budget_processes(num_robots, available_mb))
    layout = ("--single-process" if single_process
              else f"--nodes-per-process {nodes_per_process}")
    advice = ("use fewer robots" if single_process else
              f"use --nodes-per-process {max(nodes_per_process + 1, -(-num_robots // fit))} "
              f"or more (or leave it out: up chooses)")
    return (f"{layout} with {num_robots} robots takes about {needed:,.0f} MB ({processes} "
            f"policy process(es) of about {POLICY_PROCESS_MB:.0f} MB and "
            f"{POLICY_ROBOT_MB:g} MB a robot), more than {MEMORY_SHARE:.0%} of the "
            f"{available_mb:,.0f} MB available: {advice}")


def map_size_problem(size: int, available_mb: float | None) -> str:
    """Why a generated map of side `size` is refused ("" when not): generating it takes more
    than MEMORY_SHARE of the memory available."""
    if available_mb is None:
        return ""
    needed = size * size * MAP_BYTES_PER_CELL / 2**20
    if needed <= MEMORY_SHARE * available_mb:
        return ""
    return (f"--size {size}: generating a {size}x{size} map takes about {needed:,.0f} MB, more "
            f"than {MEMORY_SHARE:.0%} of the {available_mb:,.0f} MB available")
