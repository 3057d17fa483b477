"""The secured router's access control for edge devices: one credential per stream (``edge-<s>``), each allowed
only its own stream's keys. ``kmvipe bus users`` writes these entries into the router config
(``deploy/zenoh/router.json5``) for every edge user of the dictionary, so adding a camera needs no JSON5 editing.

The config keeps everything else as written (TLS, the services' and the gateway's rules, comments); only three
regions, each between a ``// kmvipe-bus-users: begin NAME`` and a ``// kmvipe-bus-users: end NAME`` comment, are
rewritten: ``rules`` (each stream's own rules), ``subjects`` and ``policies``. Key expressions come from
:mod:`keys`, so the rules follow the keys the code uses.
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Iterable

from . import keys
from .errors import ConfigError

EDGE_PREFIX = "edge-"
REGIONS = ("rules", "subjects", "policies")
SHARED_EDGE_RULES = ("edge-learns-subscribers", "ingest-alive")
"""Rules every edge policy also names; hand-written in the config because they do not depend on the stream."""
WIDTH = 118
"""Longest generated line, as the rest of the config file."""
_MARK = "// kmvipe-bus-users:"
_REGION = re.compile(rf"^(?P<indent>[ \t]*){_MARK} begin (?P<name>\w+)[^\n]*\n(?P<body>.*?)"
                     rf"^(?P<end>[ \t]*{_MARK} end (?P=name)\b)", re.MULTILINE | re.DOTALL)


def edge_user(stream: str) -> str:
    """The credential of the edge device publishing ``stream``."""
    return EDGE_PREFIX + keys.check_name(stream)


def edge_streams(users: Iterable[str]) -> list[str]:
    """The streams of the edge credentials among ``users``, in their order."""
    return [keys.check_name(u.removeprefix(EDGE_PREFIX)) for u in users if u.startswith(EDGE_PREFIX)]


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def edge_rules(stream: str) -> list[dict]:
    """What ``edge-<stream>`` may do beyond :data:`SHARED_EDGE_RULES`. A rule lets a message through when one of
    its key expressions includes the message's key, so these name this stream's keys only: a wildcard over
    streams would open every other stream to the device."""
    user = edge_user(stream)
    return [
        _rule(f"{user}-sends", "ingress", ["put"], [keys.topic(stream, keys.FRAME), keys.topic(stream, keys.EOS)]),
        _rule(f"{user}-listens", "ingress", ["declare_subscriber"], [keys.topic(stream, keys.CREDIT)]),
        _rule(f"{user}-credit", "egress", ["put"], [keys.topic(stream, keys.CREDIT)]),
        # the source token services start this stream's workers on (Bus.announce)
        _rule(f"{user}-announces", "ingress", ["liveliness_token"], [keys.source(stream)]),
    ]


def edge_subject(stream: str) -> dict:
    return {"id": edge_user(stream), "usernames": [edge_user(stream)]}


def edge_policy(stream: str) -> dict:
    own = [rule["id"] for rule in edge_rules(stream)]
    return {"id": edge_user(stream), "subjects": [edge_user(stream)], "rules": [*own, *SHARED_EDGE_RULES]}


def _entries(entries: list[dict], indent: str, compact: bool) -> list[str]:
    """JSON5 in the config's own layout: one field per line, or (``compact``) one entry per line where it fits."""
    lines: list[str] = []
    for entry in entries:
        one_line = f"{indent}{{ {', '.join(f'{k}: {json.dumps(v)}' for k, v in entry.items())} }},"
        if compact and len(one_line) <= WIDTH:
            lines.append(one_line)
            continue
        lines.append(f"{indent}{{")
        for name, value in entry.items():
            lines += _field(name, value, indent + "  ")
        lines.append(f"{indent}}},")
    return lines


def _field(name: str, value, indent: str) -> list[str]:
    """``name: value,`` with a long list wrapped under its first item."""
    head = f"{indent}{name}: "
    if not isinstance(value, list) or len(head) + len(json.dumps(value)) < WIDTH:
        return [f"{head}{json.dumps(value)},"]
    lines, line = [], head + "["
    for item in map(json.dumps, value):
        if len(line) + len(item) + 3 > WIDTH and not line.endswith("["):
            lines.append(line.rstrip())
            line = " " * (len(head) + 1)
        line += item + ", "
    return [*lines, line.removesuffix(", ") + "],"]


def _region(name: str, streams: list[str], indent: str) -> str:
    lines: list[str] = []
    for stream in streams:
        if name == "rules":
            lines.append(f"{indent}// {edge_user(stream)}: frames and end of stream in, credit out, its source token")
            lines += _entries(edge_rules(stream), indent, compact=False)
        else:
            entry = edge_subject(stream) if name == "subjects" else edge_policy(stream)
            lines += _entries([entry], indent, compact=True)
    return "".join(line + "\n" for line in lines)


def render_router_config(text: str, streams: Iterable[str]) -> str:
    """``text`` (a router config) with its edge regions holding the entries of exactly ``streams``."""
    streams = list(dict.fromkeys(keys.check_name(s) for s in streams))
    found = [m.group("name") for m in _REGION.finditer(text)]
    if sorted(found) != sorted(REGIONS):
        raise ConfigError(f"the router config needs one `{_MARK} begin NAME` / `{_MARK} end NAME` comment pair "
                          f"for each of {', '.join(REGIONS)} inside access_control (found: "
                          f"{', '.join(found) or 'none'}); deploy/zenoh/router.json5 shows where they go")

    def fill(m: re.Match) -> str:
        head = text[m.start():m.start("body")]
        return head + _region(m.group("name"), streams, m.group("indent")) + m.group("end")

    rendered = _REGION.sub(fill, text)
    check_router_config(rendered)
    return rendered


def check_router_config(text: str) -> None:
    """Raise ConfigError unless ``text`` parses as a Zenoh config whose policies name only rules and subjects it
    defines (the router would refuse to start otherwise, with a less helpful message)."""
    import zenoh  # the bus's own parser: the syntax the router will read

    try:
        acl = json.loads(zenoh.Config.from_json5(text).get_json("access_control"))
    except zenoh.ZError as exc:
        raise ConfigError(f"the router config is not a valid Zenoh config: {exc}") from exc
    rules = {r["id"] for r in acl.get("rules") or []}
    subjects = {s["id"] for s in acl.get("subjects") or []}
    for policy in acl.get("policies") or []:
        missing = sorted(set(policy["rules"]) - rules) + sorted(set(policy["subjects"]) - subjects)
        if missing:
            raise ConfigError(f"router config: policy {policy['id']!r} names undefined ids {missing}")


def read_router_config(path: Path) -> str:
    if not path.is_file():
        raise ConfigError(f"no router config at {path}: run from the repository root or give --router-config")
    return path.read_text()


def write_router_config(path: Path, streams: Iterable[str]) -> Path:
    """Rewrite the edge regions of the router config at ``path`` for ``streams``; the file is left untouched when
    the result would not be a valid config (ConfigError)."""
    text = read_router_config(path)
    rendered = render_router_config(text, streams)
    if rendered != text:
        path.write_text(rendered)
    return path
