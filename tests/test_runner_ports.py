"""Ports the runner hands its children (and the tests their services): never the same one twice."""
from __future__ import annotations

from services.runner.children import free_tcp_endpoint


def test_no_port_is_handed_out_twice():
    """The kernel gives the same free port to bind-and-release probes again (2,000 probes here: ~150 repeats), and
    two children told one port collide: a deployment test's gateway and its metrics endpoint were both given 60363
    and the gateway could not bind. 500 endpoints, all different (about 9 repeats expected without the guard)."""
    ports = [int(free_tcp_endpoint().rsplit(":", 1)[1]) for _ in range(500)]
    assert len(set(ports)) == len(ports)
