"""Network namespaces of a test's own (iproute2, as root): each joined to the host by a veth pair, so that a
process run in it (`ip netns exec NAME ...`) shares nothing with the host but what it reaches over that
network: the servers the test binds to the host side's address (`Namespaces.host`)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

import pytest


@dataclass(frozen=True)
class Namespace:
    name: str
    host: str  # the host side of its veth pair
    address: str  # its own side

    def command(self, command: list[str]) -> list[str]:
        """Return `command` run inside the namespace."""
        return ["ip", "netns", "exec", self.name, *command]


def _ip(*arguments: str) -> None:
    subprocess.run(["ip", *arguments], check=True, capture_output=True, text=True)


@contextmanager
def _namespace(tag: str, index: int, subnet: int) -> Iterator[Namespace]:
    name = f"navsim-lb-{tag}-{index}"
    host_link, own_link = f"nlb{tag}h{index}", f"nlb{tag}n{index}"  # at most 15 characters
    host, address = f"10.{subnet}.{index}.1", f"10.{subnet}.{index}.2"
    _ip("netns", "add", name)
    try:
        _ip("link", "add", host_link, "type", "veth", "peer", "name", own_link)
        _ip("link", "set", own_link, "netns", name)
        _ip("addr", "add", f"{host}/30", "dev", host_link)
        _ip("link", "set", host_link, "up")
        for arguments in (
            ("addr", "add", f"{address}/30", "dev", own_link),
            ("link", "set", own_link, "up"),
            ("link", "set", "lo", "up"),
            # The host's other addresses (another namespace's host side) through its own.
            ("route", "add", "default", "via", host),
        ):
            _ip("-n", name, *arguments)
        yield Namespace(name, host, address)
    finally:
        subprocess.run(["ip", "netns", "del", name], check=False, capture_output=True)  # its veth pair too


@contextmanager
def namespaces(count: int) -> Iterator[list[Namespace]]:
    """Yield `count` network namespaces; skip the test, saying why, on a machine that refuses them."""
    probe = subprocess.run(
        ["ip", "netns", "add", f"navsim-lb-probe-{os.getpid()}"], check=False, capture_output=True, text=True
    )
    if probe.returncode:
        pytest.skip(f"network namespaces are not allowed here (ip netns add: {probe.stderr.strip()})")
    _ip("netns", "del", f"navsim-lb-probe-{os.getpid()}")
    tag, subnet = f"{os.getpid() % 10000}", 200 + os.getpid() % 50
    with ExitStack() as stack:
        yield [stack.enter_context(_namespace(tag, index, subnet)) for index in range(1, count + 1)]
