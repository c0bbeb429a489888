"""`mapf-fleet up`'s layout advice (ROS-free): the layout it recommends for a fleet size and the
one-line warning for a layout outside what was measured to get ready."""

from mapf_fleet.fleet.up_options import (LARGE_FLEET_PROCESSES, LARGE_FLEET_ROBOTS,
                                         MAX_NODES_PER_PROCESS, layout_warning,
                                         policy_processes, recommended_nodes_per_process)


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
