"""The process layout of `mapf-fleet up` (plain Python): how many robots' policy nodes one process
hosts, the limits measured for it, and the refusal and warnings `up` gives for a layout."""

from __future__ import annotations

# Robots' nodes one process hosts at most (`--single-process`: all of them; else
# `--nodes-per-process`). Creating the nodes of one process takes time that grows with the
# square of their number (every new publisher is matched against the process's others on the
# shared topics), so thousands of them keep a fleet from its first tick for minutes or longer
# (docs/results.md, "Process layouts: what starts and what fits").
MAX_NODES_PER_PROCESS = 512
# ROS processes of one fleet on one domain that Fast DDS discovery on loopback was measured to
# handle: beyond it processes may never discover each other and the shared-memory transport can
# deadlock (docs/results.md, "Process layouts"). Above it `up` warns, not refuses.
MAX_DISCOVERED_PROCESSES = 32
# A fleet of LARGE_FLEET_ROBOTS robots or more in at most LARGE_FLEET_PROCESSES policy processes:
# the layouts measured to get ready at that size (docs/results.md, "Process layouts"; 512 as
# 16 x 32 never did). Every process discovers the per-robot
# endpoints of every other, so discovery grows with processes times robots, and every process
# starts its nodes on its own on a machine that runs them all.
LARGE_FLEET_ROBOTS = 256
LARGE_FLEET_PROCESSES = 8


def layout_problem(num_robots: int, single_process: bool, nodes_per_process: int) -> str:
    """Why this process layout is refused ("" when it is not): more than
    MAX_NODES_PER_PROCESS robots' nodes in one process."""
    per_process = num_robots if single_process else min(nodes_per_process, num_robots)
    if per_process <= MAX_NODES_PER_PROCESS:
        return ""
    layout = "--single-process" if single_process else f"--nodes-per-process {nodes_per_process}"
    return (f"{layout} would host {per_process} robots' nodes in one process; the limit is "
            f"{MAX_NODES_PER_PROCESS}, because creating them takes time growing with the square "
            f"of their number (thousands delay the first tick by minutes or longer; "
            f"docs/results.md, 'Process layouts'). Use --nodes-per-process K with "
            f"K <= {MAX_NODES_PER_PROCESS} (e.g. 8).")


def policy_processes(num_robots: int, single_process: bool, nodes_per_process: int) -> int:
    """Processes hosting the robots' policy nodes (hubs): one with --single-process."""
    return 1 if single_process else -(-num_robots // max(1, nodes_per_process))


def recommended_nodes_per_process(num_robots: int, recorder: bool = False) -> int:
    """The `--nodes-per-process` `up` recommends for `num_robots`: a large fleet (at least
    LARGE_FLEET_ROBOTS) in LARGE_FLEET_PROCESSES processes (at most MAX_NODES_PER_PROCESS nodes
    each); a smaller one in as few as keep every ROS process within MAX_DISCOVERED_PROCESSES
    (1: a process per robot)."""
    if num_robots >= LARGE_FLEET_ROBOTS:
        return min(-(-num_robots // LARGE_FLEET_PROCESSES), MAX_NODES_PER_PROCESS)
    return max(1, -(-num_robots // max(1, MAX_DISCOVERED_PROCESSES - 1 - int(recorder))))


def layout_warning(num_robots: int, single_process: bool, nodes_per_process: int,
                   recorder: bool = False) -> str:
    """A warning ("" when none) when the layout has more policy processes than a large fleet
    was measured to get ready with (LARGE_FLEET_PROCESSES from LARGE_FLEET_ROBOTS robots), or
    needs more ROS processes (the simulator or aggregator, one per group of robots' nodes, the
    recorder) than MAX_DISCOVERED_PROCESSES."""
    hubs = policy_processes(num_robots, single_process, nodes_per_process)
    if num_robots >= LARGE_FLEET_ROBOTS and hubs > LARGE_FLEET_PROCESSES:
        suggest = recommended_nodes_per_process(num_robots, recorder)
        if nodes_per_process < suggest:
            return (f"warning: {num_robots} robots in {hubs} policy processes; fleets of "
                    f"{LARGE_FLEET_ROBOTS}+ robots were measured to get ready only in "
                    f"{LARGE_FLEET_PROCESSES} or fewer (docs/results.md, 'Process layouts'), "
                    f"since DDS discovery grows with processes times robots "
                    f"and each process starts its nodes on its own. Use --nodes-per-process "
                    f"{suggest} ({policy_processes(num_robots, False, suggest)} processes).")
    processes = 1 + hubs + int(recorder)
    if processes <= MAX_DISCOVERED_PROCESSES:
        return ""
    suggest = recommended_nodes_per_process(num_robots, recorder)
    return (f"warning: this layout starts {processes} ROS processes on one domain; Fast DDS "
            f"discovery on loopback was measured reliable up to about "
            f"{MAX_DISCOVERED_PROCESSES} (above it processes may never see each other and robots "
            f"miss decisions). Use --nodes-per-process {suggest} or more.")
