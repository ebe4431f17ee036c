"""Collectives inside loops, read from an optimised HLO module's text (``compiled.as_text()``).

A computation is "in a loop" when a ``while`` names it as its condition or body, or when
such a computation calls it (``calls=``, ``to_apply=``, branches, nested whiles),
transitively. Used by the multi-device test of the closed loop: a collective there makes
every device wait each iteration for the others.
"""

import re

COLLECTIVES = ("all-reduce", "all-gather", "collective-permute", "all-to-all",
               "reduce-scatter", "collective-broadcast")

_HEADER = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_CALLEE = re.compile(r"(?:condition|body|to_apply|calls|branch_computations|"
                     r"called_computations)=\{?(%?[\w.\-]+(?:,\s*%?[\w.\-]+)*)\}?")
_WHILE = re.compile(r"\swhile\(.*?condition=%?([\w.\-]+), body=%?([\w.\-]+)")


def computations(text: str) -> dict:
    """Computation name -> its body text."""
    comps, name, body = {}, None, []
    for line in text.splitlines():
        if name is None:
            m = _HEADER.match(line)
            if m:
                name, body = m.group(1), []
        elif line.strip() == "}":
            comps[name] = "\n".join(body)
            name = None
        else:
            body.append(line)
    return comps


def collectives_in_loops(text: str) -> tuple[int, int, dict]:
    """(while loops, computations in loops, {collective op: count in those computations})."""
    comps = computations(text)
    roots = set()
    for body in comps.values():
        for m in _WHILE.finditer(body):
            roots |= {m.group(1), m.group(2)}
    seen, todo = set(), list(roots)
    while todo:
        c = todo.pop()
        if c in seen or c not in comps:
            continue
        seen.add(c)
        for m in _CALLEE.finditer(comps[c]):
            todo += [n.strip().lstrip("%") for n in m.group(1).split(",")]
    found = {}
    for c in seen:
        for op in COLLECTIVES:
            n = len(re.findall(r"\s" + op + r"(?:-start)?\(", comps[c]))
            if n:
                found[op] = found.get(op, 0) + n
    return sum(len(_WHILE.findall(b)) for b in comps.values()), len(seen), found
