"""The processes a test started, found from /proc: what a test needs to watch or confine a whole run."""

from __future__ import annotations

from pathlib import Path


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (by /proc's parent links); ``pid`` itself not included."""
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue            # gone meanwhile
            kids.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        below = kids.get(todo.pop(), [])
        out.update(below)
        todo += below
    return out
