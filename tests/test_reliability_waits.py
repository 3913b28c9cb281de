"""A role waiting for a learner that nobody serves: one line at first, then every 30 s (not once a
second), saying when the session has no link at all."""

from __future__ import annotations

import logging

import pytest

from services.messaging import bus
from services.roles import role
from tests.e2e import unique_run


def test_waiting_for_the_learner_is_said_once_and_names_a_missing_link(caplog) -> None:
    conf = bus.make_config(listen=[bus.loopback_endpoint(bus.free_tcp_port())])  # alone: nobody to reach
    with bus.session_scope(conf) as session, caplog.at_level(logging.INFO, logger="mam.role"):
        assert role.connected(session) is False
        with pytest.raises(TimeoutError, match="no learner published a config"):
            role.fetch_config(session, unique_run("nobody"), bus.RejectLog(), timeout=3.5)
    lines = [r.getMessage() for r in caplog.records if "waiting for the learner" in r.getMessage()]
    assert len(lines) == 1, lines  # was one a second
    assert "no link to any router or peer" in lines[0]
