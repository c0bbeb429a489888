"""The aggregator's warning for robots not at their waypoints says how long the tick really
waited (issue 40, item 8: real-robot runs printed "not at their waypoints after 10.0 s", the
`arrival_timeout`, after ticks of 0.6 s), and why a wait ended before the timeout."""

from __future__ import annotations

import pytest


@pytest.mark.ros
def test_the_arrival_warning_states_the_time_waited():
    from mapf_fleet.ros.aggregator_node import arrival_warning

    assert arrival_warning(7, [1, 3], 10.02, 10.0, False) == (
        "tick 7: robots [1, 3] not at their waypoints after 10.0 s")
    early = arrival_warning(7, [1], 0.6, 10.0, True)
    assert early == ("tick 7: robots [1] not at their waypoints after 0.6 s (the run is "
                     "stopping; arrival_timeout 10 s)")
    assert "after 0.6 s (arrival_timeout 10 s)" in arrival_warning(7, [1], 0.6, 10.0, False)
