"""The run plan: the dataflow of a run as data — its nodes, their hosts, the keys each writes and reads.

``build_plan(scenario, placement=...)`` → :class:`RunPlan`; ``load_placement("hosts.toml")`` → a
:class:`Placement`; ``flocktrack plan SCENARIO`` prints one (text, json, mermaid).
"""

from .build import build_plan
from .model import Host, Node, RestartPolicy, RunPlan
from .placement import Placement, load_placement, parse_placement

__all__ = ["build_plan", "Host", "Node", "RestartPolicy", "RunPlan", "Placement", "load_placement", "parse_placement"]
