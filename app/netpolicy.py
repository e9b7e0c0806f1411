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


def _origin_and_path(url: str) -> tuple[str, str, int, str] | None:
    try:
        parts = urlsplit(url.strip())
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        return None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        return None
    return parts.scheme, parts.hostname.lower(), port, parts.path.rstrip("/") + "/"


def dicomweb_target_problem(url: str, settings: Settings) -> str | None:
    """None when `url` lies under one of RIBPULL_DICOMWEB_URLS (same scheme, host and port, and a path
    below the configured one); else the reason. A PACS usually sits on a private network, so unlike
    webhooks the rule is an explicit list set by the operator, and nothing else is ever contacted."""
    want = _origin_and_path(url)
    if want is None:
        return "it is not an absolute http(s) URL"
    bases = [b for b in (_origin_and_path(u) for u in settings.dicomweb_urls.split(",") if u.strip()) if b]
    if not bases:
        return "this server has no DICOMweb servers configured (RIBPULL_DICOMWEB_URLS)"
    for base in bases:
        if want[:3] == base[:3] and want[3].startswith(base[3]):
            return None
    return "it is not one of this server's DICOMweb servers (RIBPULL_DICOMWEB_URLS)"
