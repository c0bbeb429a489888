"""`mapf-fleet up`'s layout advice (ROS-free): the layout it recommends for a fleet size and the
one-line warning for a layout outside what was measured to get ready; the layout it chooses
from the robot count and the memory available when --nodes-per-process is not given, and the
layouts and maps it refuses for memory (`ros/layout_choice.py`, pure functions of the count and
the memory)."""

import pytest

from mapf_fleet.fleet.up_options import (LARGE_FLEET_PROCESSES, LARGE_FLEET_ROBOTS,
                                         MAX_NODES_PER_PROCESS, layout_warning,
                                         UpError, policy_processes,
                                         recommended_nodes_per_process)
from mapf_fleet.ros.layout_choice import (MEMORY_SHARE, POLICY_PROCESS_MB, available_memory_mb,
                                          choose_layout, fleet_memory_mb, layout_memory_problem,
                                          map_size_problem)


def test_a_large_fleet_is_recommended_the_measured_process_count():
    assert (LARGE_FLEET_ROBOTS, LARGE_FLEET_PROCESSES) == (256, 8)
    assert recommended_nodes_per_process(512) == 64  # 8 x 64: ready in the measurements
    assert recommended_nodes_per_process(256) == 32
    assert recommended_nodes_per_process(1000) == 125
    assert policy_processes(1000, False, recommended_nodes_per_process(1000)) == 8
    # beyond 8 x MAX_NODES_PER_PROCESS robots the per-process limit wins
    assert recommended_nodes_per_process(10000) == MAX_NODES_PER_PROCESS
    # smaller fleets: as few per process as keep every process discovered
    assert recommended_nodes_per_process(8) == 1
    assert recommended_nodes_per_process(128) == 5


def test_up_warns_512_robots_in_16_processes_and_names_the_layout_that_got_ready():
    warning = layout_warning(512, False, 32)  # 16 x 32: never got ready when measured
    assert warning.startswith("warning: 512 robots in 16 policy processes")
    assert "--nodes-per-process 64 (8 processes)" in warning
    assert "discovery" in warning and "\n" not in warning
    assert "--nodes-per-process 64" in layout_warning(512, False, 1)  # a process per robot
    assert "--nodes-per-process 32" in layout_warning(256, False, 16)
    # the layouts measured ready, more robots per process, one process: no warning
    assert layout_warning(512, False, 64) == "" and layout_warning(256, False, 32) == ""
    assert layout_warning(512, False, 128) == "" and layout_warning(512, True, 1) == ""
    # below the large-fleet size only the discovery limit of processes applies
    assert layout_warning(LARGE_FLEET_ROBOTS - 1, False, 16) == ""


# -- the layout `up` chooses when --nodes-per-process is not given (ros/layout_choice.py) ------

PLENTY = 1e9  # MB: memory no fleet here runs short of


def test_the_layout_follows_the_robot_count_when_memory_is_plenty():
    assert choose_layout(8, PLENTY) == (1, "")  # a process per robot, nothing to say
    k, note = choose_layout(512, PLENTY)
    assert k == 64 and "\n" not in note
    assert note.startswith("512 robots in 8 policy process(es) of up to 64 robots "
                           "(--nodes-per-process 64, chosen for the robot count")
    assert choose_layout(128, PLENTY)[0] == recommended_nodes_per_process(128)
    assert choose_layout(512, None)[0] == 64  # memory unknown: the count alone


def test_the_layout_has_fewer_larger_processes_when_memory_is_short():
    # the machine: 512 robots as a process per robot took all of 24 GiB
    assert fleet_memory_mb(512, 512) > MEMORY_SHARE * 24 * 1024
    k, note = choose_layout(512, 24 * 1024)
    assert k == 64  # 8 x 64 fits 24 GiB
    available = 2500.0  # room for only a few processes
    k, note = choose_layout(512, available)
    processes = -(-512 // k)
    assert 1 <= processes < 8 and fleet_memory_mb(512, processes) <= MEMORY_SHARE * available
    assert fleet_memory_mb(512, processes + 1) > MEMORY_SHARE * available  # as many as fit
    assert "memory available" in note and f"--nodes-per-process {k}" in note
    k, _ = choose_layout(20, 2500.0)  # small fleet: a process per robot would not fit either
    assert k > 1 and fleet_memory_mb(20, -(-20 // k)) <= MEMORY_SHARE * 2500.0


def test_a_fleet_that_cannot_fit_is_refused_before_anything_starts():
    with pytest.raises(UpError, match=r"^512 robots need about .* MB .*available: use fewer"):
        choose_layout(512, 500.0)


def test_a_given_layout_that_does_not_fit_is_refused_in_one_line():
    problem = layout_memory_problem(512, False, 1, 24 * 1024)
    assert problem.startswith("--nodes-per-process 1 with 512 robots takes about")
    assert "use --nodes-per-process" in problem and "\n" not in problem
    assert layout_memory_problem(512, False, 64, 24 * 1024) == ""
    assert layout_memory_problem(8, False, 1, 24 * 1024) == ""
    assert layout_memory_problem(512, False, 1, None) == ""  # unknown: not refused
    assert layout_memory_problem(4000, True, 1, 1000.0).startswith("--single-process with 4000")
    assert POLICY_PROCESS_MB > 0


def test_a_generated_map_too_large_for_memory_is_refused():
    problem = map_size_problem(100000, 24 * 1024)
    assert problem.startswith("--size 100000: generating a 100000x100000 map takes about")
    assert map_size_problem(80, 24 * 1024) == "" and map_size_problem(100000, None) == ""


def test_available_memory_is_read_from_meminfo(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       32000000 kB\nMemAvailable:   20480000 kB\n")
    assert available_memory_mb(str(meminfo)) == 20000.0
    meminfo.write_text("MemTotal: 1 kB\n")
    assert available_memory_mb(str(meminfo)) is None
    assert available_memory_mb(str(tmp_path / "missing")) is None
