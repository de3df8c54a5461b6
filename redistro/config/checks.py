"""Checks across fields, run once the config is built: names, hosts, ports.

- Robot names become parts of IPC object names (``/redistro.<session>.esc.<robot>...``):
  letters, digits, ``_`` and ``-``, 1-32 characters.
- ``ddm.peers`` entries are ``host:port``; hosts (``listen_host``,
  ``esc_hosts``, peers) are IPv4/IPv6 addresses or host names; the reflective
  group is an IPv4 multicast address; ``esc_hosts``/``esc_ports`` and the
  plant's per-robot tables name robots of the config.
- Zenoh endpoints are ``tcp|udp|tls|quic/<host>:<port>`` with a port 1-65535
  (a listen on port 0 could not be found by the other nodes); the zenoh
  group is a name of the IPC alphabet (it becomes a key expression's
  chunk: ``*``, ``$`` or ``/`` would make it a wildcard over other groups).
- The robots' bases stand apart (:data:`BASE_CLEARANCE_M`): two arms on
  one spot are refused, not simulated into each other.
"""

from __future__ import annotations

import ipaddress
import re
from typing import TYPE_CHECKING

from redistro.errors import ConfigError, shown

if TYPE_CHECKING:
    from redistro.config.model import Config

ROBOT_NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
ZENOH_GROUP = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
ENDPOINT = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[^/:\[\]]+):([0-9]{1,5})$")
# the arm's base link is a cylinder of about 0.1 m radius: two bases closer
# than this overlap (or leave the arms no room to move at all)
BASE_CLEARANCE_M = 0.3
HOST_NAME = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
    r"(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)


def _cut(value: object) -> str:
    return shown(value)


def valid_host(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return bool(HOST_NAME.match(text))


def check_config(cfg: Config) -> None:
    from redistro.drivers.io.bank import MAX_ROBOTS

    if len(cfg.robots) > MAX_ROBOTS:
        raise ConfigError(
            f"{cfg.origin('robots')}: robots: at most {MAX_ROBOTS} robots in a group (the "
            f"simulated plant's register bank), got {len(cfg.robots)}"
        )
    for name in cfg.robots:
        if not ROBOT_NAME.match(name):
            raise ConfigError(
                f"{cfg.origin('robots.' + name)}: robots: a robot name is 1-32 letters, digits, "
                f"_ or -, got {_cut(name)}"
            )
    d = cfg.ddm
    if not valid_host(d.listen_host):
        raise ConfigError(
            f"{cfg.origin('ddm.listen_host')}: ddm.listen_host: expected an IP address or a "
            f"host name, got {_cut(d.listen_host)}"
        )
    try:
        group = ipaddress.ip_address(d.group)
        ok = group.version == 4 and group.is_multicast
    except ValueError:
        ok = False
    if not ok:
        raise ConfigError(
            f"{cfg.origin('ddm.group')}: ddm.group: expected an IPv4 multicast address "
            f"(224.0.0.0/4), got {_cut(d.group)}"
        )
    for key, table in (("ddm.esc_hosts", d.esc_hosts), ("ddm.esc_ports", d.esc_ports)):
        for robot, value in table.items():
            if robot not in cfg.robots:
                raise ConfigError(
                    f"{cfg.origin(key)}: {key}.{_cut(robot)[1:-1]}: no robot of that name "
                    f"(known: {', '.join(cfg.robots)})"
                )
            if key == "ddm.esc_hosts" and not valid_host(str(value)):
                raise ConfigError(
                    f"{cfg.origin(key)}: {key}.{robot}: expected an IP address or a host "
                    f"name, got {_cut(value)}"
                )
    for i, peer in enumerate(d.peers):
        host, sep, port = peer.rpartition(":")
        host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
        if (
            not sep
            or not valid_host(host)
            or not (port.isascii() and port.isdigit())
            or not 0 < int(port) < 65536
        ):
            raise ConfigError(
                f"{cfg.origin('ddm.peers')}: ddm.peers[{i}]: expected host:port with a port "
                f"1-65535, got {_cut(peer)}"
            )
    z = d.zenoh
    if z.group and not ZENOH_GROUP.match(z.group):
        raise ConfigError(
            f"{cfg.origin('ddm.zenoh.group')}: ddm.zenoh.group: expected 1-64 letters, digits, "
            f"_ or - (no key-expression wildcards), got {_cut(z.group)}"
        )
    listens = (("ddm.zenoh.listen", z.listen), ("ddm.zenoh.connect", z.connect))
    for key, endpoints in (*listens, ("ros2.listen", cfg.ros2.listen)):
        for i, e in enumerate(endpoints):
            problem = endpoint_problem(e)
            if problem:
                raise ConfigError(f"{cfg.origin(key)}: {key}[{i}]: {problem}")
    _check_objects(cfg)
    names = list(cfg.robots)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            pa, pb = cfg.robots[a].base_xyz_m, cfg.robots[b].base_xyz_m
            gap = sum((x - y) ** 2 for x, y in zip(pa, pb, strict=True)) ** 0.5
            if gap < BASE_CLEARANCE_M:
                where = min(cfg.origin(f"robots.{r}.base_xyz_m") for r in (a, b))  # --set first
                raise ConfigError(
                    f"{where}: robots.{b}.base_xyz_m: "
                    f"{gap:.3f} m from {a}'s base, at least {BASE_CLEARANCE_M} m apart "
                    "(the arms would stand in each other)"
                )


def _check_objects(cfg: Config) -> None:
    for name, o in cfg.workcell.objects.items():
        problem = o.hole_problem()
        if problem:
            key = f"workcell.objects.{name}"
            raise ConfigError(f"{cfg.origin(key)}: {key}: {problem}")


def endpoint_problem(text: str) -> str:
    """Why a zenoh endpoint is refused ('' when it is fine)."""
    m = ENDPOINT.match(text)
    if m is None:
        return f"expected tcp|udp|tls|quic/host:port, got {_cut(text)}"
    host = m.group(2)
    host = host[1:-1] if host.startswith("[") else host
    if not valid_host(host):
        return f"expected an IP address or a host name, got {_cut(host)}"
    if not 0 < int(m.group(3)) < 65536:
        return f"expected a port 1-65535, got {m.group(3)}"
    return ""
