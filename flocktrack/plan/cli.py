"""``flocktrack plan SCENARIO [--placement hosts.toml] [--format text|json|mermaid] [--check]``.

Prints the run plan: every node with its host, restart policy, writes and reads — as text for a person, as
JSON for tools (``{"run", "hosts": [...], "nodes": [{"name", "kind", "host", "writes", "reads", ...}]}``, the
same file a run writes as ``plan.json``), or as a Mermaid flowchart of who feeds whom (the sensors drawn as
one box). ``--check`` validates a placement against the scenario — every node placed once, every host's
address resolvable — and says so, or names the file, the key and the fix.
"""

from __future__ import annotations

import sys

from .build import build_plan
from .model import Node, RunPlan
from .placement import load_placement


def intersects(a: str, b: str) -> bool:
    """Do two key expressions (``*`` one chunk, ``**`` any number) match a common key?"""
    x, y = a.split("/"), b.split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(x) and j == len(y):
            return True
        if i < len(x) and x[i] == "**":
            return rec(i + 1, j) or (j < len(y) and rec(i, j + 1))
        if j < len(y) and y[j] == "**":
            return rec(i, j + 1) or (i < len(x) and rec(i + 1, j))
        if i == len(x) or j == len(y):
            return False
        return (x[i] == y[j] or "*" in (x[i], y[j])) and rec(i + 1, j + 1)

    return rec(0, 0)


def _restart(n: Node) -> str:
    r = n.restart
    return r.mode + (f" (≤ {r.max_restarts})" if r.mode == "on-failure" else "")


def as_text(plan: RunPlan) -> str:
    lines = [f"run {plan.run} ({plan.mode}, {plan.scenario}): {len(plan.nodes)} nodes on {len(plan.hosts)} "
             f"host{'s' if plan.multi_host else ''}"]
    for h in plan.hosts:
        lines.append(f"\nhost {h.name}  {h.endpoint}" + (f"  listens on {h.listen}" if plan.multi_host else ""))
        for n in plan.on(h.name):
            cmd = f"python -m {n.module} {' '.join(n.args)}".rstrip() if n.module else "(the launcher itself)"
            lines.append(f"  {n.name:<13} {n.kind:<9} restart {_restart(n):<16} {cmd}")
            if n.writes:
                lines.append(f"  {'':13} writes {', '.join(n.writes)}")
            if n.reads:
                lines.append(f"  {'':13} reads  {', '.join(n.reads)}")
    return "\n".join(lines) + "\n"


def _box(n: Node, plan: RunPlan) -> tuple[str, str]:
    """A node's Mermaid id and label; the sensors of a host share one box."""
    if n.kind == "agent":
        ids = [int(m.id) for m in plan.on(n.host) if m.kind == "agent"]
        return f"agents_{n.host}", f"agent/{min(ids)}–{max(ids)}<br/>{len(ids)} sensors"
    return n.slug.replace("-", "_"), n.name


def as_mermaid(plan: RunPlan) -> str:
    """A flowchart: a box per node (one per host for the sensors), an arrow writer → reader per key family."""
    out = ["flowchart LR"]
    boxes: dict[str, tuple[str, Node]] = {}
    for h in plan.hosts:
        out.append(f"  subgraph host_{h.name}[\"host {h.name}\"]")
        for n in plan.on(h.name):
            if n.kind == "router":
                continue
            bid, label = _box(n, plan)
            if bid not in boxes:
                boxes[bid] = (label, n)
                out.append(f"    {bid}[\"{label}\"]")
        out.append("  end")
    edges: dict[tuple[str, str], set[str]] = {}
    for wid, (_, w) in boxes.items():
        for rid, (_, r) in boxes.items():
            for k in w.writes:
                if any(intersects(k, q) for q in r.reads):
                    fam = "/".join("*" if c.isdigit() else c for c in k.split("/"))
                    if not (wid == rid and "/to/" not in fam):
                        edges.setdefault((wid, rid), set()).add(fam)
    for (wid, rid), keys in edges.items():
        label = ", ".join(sorted(keys)[:3]) + (" …" if len(keys) > 3 else "")
        out.append(f"  {wid} -->|\"{label}\"| {rid}")
    return "\n".join(out) + "\n"


def cmd_plan(args) -> int:
    from agent.scenario import parse_scenario, scenario_data

    sc = parse_scenario(scenario_data(args.scenario, args.set or []), args.scenario)
    placement = load_placement(args.placement) if args.placement else None
    plan = build_plan(sc, placement=placement, dashboard=not args.no_dashboard)
    if args.check:
        if placement is None:
            print(f"{args.scenario}: {len(plan.nodes)} nodes on one host (no --placement to check)")
            return 0
        placement.check_reachable()
        counts = ", ".join(f"{h.name}: {len(plan.on(h.name))}" for h in plan.hosts)
        print(f"{args.placement}: every node of {args.scenario} placed once ({counts} nodes); every host resolves")
        return 0
    text = {"text": as_text, "json": RunPlan.to_json, "mermaid": as_mermaid}[args.format](plan)
    sys.stdout.write(text)
    return 0


def register(subparsers) -> None:
    """Add ``flocktrack plan`` to the CLI."""
    from flocktrack.resources import add_scenario_argument

    p = subparsers.add_parser("plan", help="print a scenario's run plan: its nodes, hosts, writes and reads",
                              description=__doc__.split("\n\n")[0])
    add_scenario_argument(p)
    p.add_argument("--placement", metavar="HOSTS.toml", help="place the nodes on the hosts of this file")
    p.add_argument("--format", choices=["text", "json", "mermaid"], default="text")
    p.add_argument("--check", action="store_true", help="validate --placement against the scenario and stop")
    p.add_argument("--no-dashboard", action="store_true", help="a run without the dashboard's node")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scenario key")
    p.set_defaults(fn=cmd_plan)
