"""``flocktrack fault``: a control verb checked here, sent, and its answer waited for (kubectl-like).

The verb and its arguments are checked before anything is sent, by the same :func:`agent.wire.command`
the world, the launcher and the sensors apply; the argument names a verb takes are the fields of its typed
command (:data:`agent.wire.COMMAND_TYPES`), so an unknown verb or argument name is refused with a "did you mean".
The command then carries a request id (``req``), and the answer is the message that echoes it: the
world's ``world/event`` (verb = the command's, at the tick it takes effect; ``rejected`` with the reason)
or, for kill and restart, the launcher's ``launcher/event`` (``applied``, ``reason``). A restart is "back"
once the restarted member's liveliness token is seen again. ``outlier_burst`` has no answer: the sensors
apply it to their next measurements and acknowledge nothing, so it is reported as *sent*.

Exit codes (:data:`APPLIED`, :data:`REFUSED`, :data:`NO_ANSWER`) follow kubectl: 0 applied (or sent, for a
verb without an answer), 1 refused (here or by the run), 2 no answer (or nothing to send it to, or an
unknown verb or argument name).
"""

from __future__ import annotations

import time
import uuid
from dataclasses import dataclass, fields
from typing import Any

from agent.suggest import did_you_mean
from agent.wire import COMMAND_TYPES, CONTROL_VERBS, MAX_LIST_LEN, Control, Message, WireError, command

APPLIED, REFUSED, NO_ANSWER = 0, 1, 2

#: verbs whose executor publishes no answer (the sensors apply an outlier burst to their next measurements)
UNANSWERED = frozenset({"outlier_burst"})
LAUNCHER_VERBS = frozenset({"kill", "restart"})

#: arguments any verb may carry: the request id its answer echoes (agent/wire.py ``request_id``)
GENERIC_ARGS = ("req",)


class UsageError(ValueError):
    """A command line that names nothing the run knows (exit 2, nothing sent)."""


class UnknownVerbError(UsageError):
    """Not a control verb (the message says which are, and what was probably meant)."""


class UnknownArgumentError(UsageError):
    """An argument name the verb does not take (the message says which it takes, and what was probably meant)."""


def arg_names(verb: str) -> tuple[str, ...]:
    """The argument names ``verb`` takes, :data:`GENERIC_ARGS` last. ``inject`` carries a fault event flat
    in its args: the keys of a ``[[faults.events]]`` entry (agent/scenario.py ``FaultEventCfg``) but
    start/heal (it starts now; its duration is ``ticks``)."""
    names = [f.name for f in fields(COMMAND_TYPES[verb]) if f.name not in ("verb", "event")]
    if verb == "inject":
        from agent.scenario import FaultEventCfg

        names += [f.name for f in fields(FaultEventCfg) if f.name not in ("start", "heal")]
    return (*names, *GENERIC_ARGS)


def _check_names(verb: str, args: dict[str, Any]) -> None:
    known = arg_names(verb)
    for name in args:
        if name not in known:
            own = [k for k in known if k not in GENERIC_ARGS]
            takes = f"{verb} takes: {', '.join(own)}" if own else f"{verb} takes no arguments"
            raise UnknownArgumentError(f"{verb} takes no argument {name!r}; "
                                       f"{did_you_mean(name, known, quote=chr(39))}{takes}")


@dataclass
class Answer:
    code: int                 #: APPLIED | REFUSED | NO_ANSWER
    text: str                 #: one line for the terminal
    k: int | None = None      #: the tick it takes effect on (world verbs)
    fault_id: int | None = None  #: inject: the id to heal it by


def check(verb: str, args: dict[str, Any], n: int | None = None) -> None:
    """Refuse here what the run would refuse: :class:`UnknownVerbError`, :class:`UnknownArgumentError`, or
    :class:`agent.wire.WireError` naming the argument. ``n``: the flock's size when known (a local run's);
    else the bounds that depend on it are the run's to check."""
    if verb not in CONTROL_VERBS:
        raise UnknownVerbError(f"unknown verb {verb!r}; {did_you_mean(verb, CONTROL_VERBS, quote=chr(39))}"
                               f"the verbs are: {', '.join(CONTROL_VERBS)}")
    _check_names(verb, args)
    if n is None:
        groups = args.get("groups")
        n = len(groups) if verb == "partition" and isinstance(groups, list) and groups else MAX_LIST_LEN
    cmd = command(verb, args, n)
    if verb == "inject":
        from agent.scenario import ScenarioError, parse_fault_event

        try:
            parse_fault_event(cmd.event, n)
        except ScenarioError as exc:
            raise WireError("bad_field", str(exc)) from None


def send(bus, verb: str, args: dict[str, Any], timeout_s: float = 5.0) -> Answer:
    """Send ``control/<verb>`` on ``bus`` (a :class:`agent.bus.ZenohBus` of the run) and wait for its answer."""
    req = uuid.uuid4().hex[:12]
    answers: list[tuple[str, Control, float]] = []
    members: dict[str, bool] = {}

    def on_event(key: str, msg: Message) -> None:
        if isinstance(msg, Control) and msg.args.get("req") == req:
            answers.append((key, msg, time.time()))

    bus.subscribe("world/event", on_event)
    bus.subscribe("launcher/event", on_event)
    bus.watch_members(lambda name, alive: members.__setitem__(name, alive))
    end = time.monotonic() + timeout_s
    if not bus.await_subscriber(f"control/{verb}", timeout_s):
        return Answer(NO_ANSWER, f"nobody in run {bus.prefix[3:-1]} listens to control/{verb} "
                                 f"(members seen: {', '.join(sorted(m for m, a in members.items() if a)) or 'none'})")
    bus.publish(f"control/{verb}", Control(verb=verb, args={**args, "req": req}))
    if verb in UNANSWERED:
        bus.poll(0.2)   # let it leave
        return Answer(APPLIED, f"sent control/{verb} {args} (no acknowledgement for this verb: the sensors apply it)")
    while not answers and time.monotonic() < end:
        bus.poll(0.05)
    if not answers:
        return Answer(NO_ANSWER, f"no answer to control/{verb} within {timeout_s:g} s (is the run paused "
                                 f"waiting, or has it ended?)")
    key, msg, at = answers[0]
    if key == "launcher/event":
        return _launcher_answer(bus, verb, msg, members, end=end, at=at)
    if msg.verb == "rejected":
        return Answer(REFUSED, f"refused: {msg.args.get('reason') or 'bad arguments'}", k=msg.k)
    fid = msg.args.get("id") if verb == "inject" else None
    text = f"applied: {verb} at tick {msg.k}"
    if fid is not None:
        fid = int(fid)
        text += f", fault id {fid} (heal it with: flocktrack fault heal_fault id={fid})"
    return Answer(APPLIED, text, k=msg.k, fault_id=fid)


def when_applied(k: int | None, at: float) -> str:
    """When the launcher applied a kill / restart: at the newest tick it had seen, or — before the first
    tick (it answers k = 0 then) — at the wall-clock time its answer came (``at``, epoch seconds)."""
    return f"at tick {k}" if k else f"at {time.strftime('%H:%M:%S', time.localtime(at))}"


def _launcher_answer(bus, verb: str, msg: Control, members: dict[str, bool], *, end: float, at: float) -> Answer:
    """The launcher's answer to kill / restart, at the newest tick the launcher had seen (k = 0 before the
    first tick: then the time it came is printed instead)."""
    name = f"agent/{int(msg.args['agent'])}" if msg.args.get("agent") is not None else "?"
    if not msg.args.get("applied"):
        return Answer(REFUSED, f"refused: {msg.args.get('reason') or 'by the launcher'}")
    k = msg.k or None
    when = when_applied(k, at)
    if verb == "kill":
        return Answer(APPLIED, f"applied {when}: {name} killed (SIGKILL); "
                               f"`flocktrack fault restart agent=...` brings it back", k=k)
    while not members.get(name) and time.monotonic() < end:   # restart: back once its token is seen
        bus.poll(0.05)
    if members.get(name):
        return Answer(APPLIED, f"applied {when}: {name} restarted and back in the run", k=k)
    return Answer(APPLIED, f"applied {when}: {name} restarted (not back in the run yet)", k=k)
