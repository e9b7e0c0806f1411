"""Which hosts a completion webhook may target (checked by the API at submission -> 422, and again by
the worker right before each POST, so a DNS name that later resolves elsewhere is still refused).

Always refused: loopback, link-local, unspecified, multicast and reserved addresses, and the service's
own ports (API, Redis) on any non-public address. Private ranges (10/8, 172.16/12, 192.168/16, fc00::/7,
...) only when they are inside RIBPULL_WEBHOOK_ALLOWLIST (comma-separated CIDRs or IPs).
"""

from __future__ import annotations

import ipaddress
import socket
from urllib.parse import urlsplit

from .settings import Settings

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def allowlist(settings: Settings) -> list[IPNetwork]:
    nets = []
    for item in settings.webhook_allowlist.split(","):
        item = item.strip()
        if item:
            try:
                nets.append(ipaddress.ip_network(item, strict=False))
            except ValueError:
                continue  # unusable entries allow nothing
    return nets


def _own_ports(settings: Settings) -> set[int]:
    ports = {settings.port}
    if settings.redis_port:
        ports.add(settings.redis_port)
    return ports


def check_ip(ip: ipaddress.IPv4Address | ipaddress.IPv6Address, port: int, settings: Settings) -> str | None:
    """Why `ip:port` is not an acceptable webhook target, or None."""
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if ip.is_loopback or ip.is_unspecified:
        return f"{ip} is a loopback address"
    if ip.is_link_local:
        return f"{ip} is a link-local address"
    if ip.is_multicast or (ip.is_reserved and not ip.is_private):
        return f"{ip} is a multicast or reserved address"
    if not ip.is_global:
        if port in _own_ports(settings):
            return f"port {port} on {ip} is one of this service's own ports"
        if not any(ip in net for net in allowlist(settings)):
            return f"{ip} is a private address; allow it with RIBPULL_WEBHOOK_ALLOWLIST"
    return None


def webhook_target_problem(url: str, settings: Settings) -> str | None:
    """None when every address `url`'s host resolves to is acceptable; else the reason."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        return "the URL has an invalid port"
    try:
        ip = ipaddress.ip_address(host.split("%")[0])
        ips = [ip]
    except ValueError:
        try:
            infos = socket.getaddrinfo(host, port, proto=socket.IPPROTO_TCP)
        except OSError:
            return f"the host '{host[:100]}' does not resolve"
        ips = [ipaddress.ip_address(i[4][0].split("%")[0]) for i in infos]
        if not ips:
            return f"the host '{host[:100]}' does not resolve"
    for ip in ips:
        why = check_ip(ip, port, settings)
        if why:
            return why
    return None
