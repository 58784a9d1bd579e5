"""The whole-grammar checks of the compiler: what no single type or law can see.

They run after lowering (`ssgc.compile`), on the lowered types and rules, and report findings
rather than raising, so that every problem of a document is reported at once: files named
outside the grammar's directory, labels and models naming two types, the root produced by a
rule, recursion without a bound, unreachable types.
"""

from __future__ import annotations

import os
from pathlib import Path

from ssgc import dsl
from ssgc.ir import Loc, NodeType, Rule

MAX_CYCLES_REPORTED = 20  # a grammar with more unbounded cycles gets the first ones

Finding = tuple[str, Loc, str]  # severity ("error" or "warning"), document path, message


def check_references(
    types: list[NodeType],
    rules: list[Rule],
    root: int | None,
    base_dir: Path | None,
    allow_outside: bool,
) -> list[Finding]:
    """The root is no rule's child; labels and models name one type each; named files are
    usable.  `root` is None when the root's name is unknown."""
    checks = _Checks(types, base_dir, allow_outside)
    checks.check_root_not_produced(rules, root)
    checks.check_labels(types)
    checks.check_files(types)
    return checks.findings


def check_recursion(types: list[NodeType], rules: list[Rule]) -> list[Finding]:
    """Every cycle is bounded.  Rules with errors are left out, which can hide a cycle but
    never make one up, so this runs on a grammar with other errors too."""
    checks = _Checks(types, None, False)
    checks.check_recursion(types, rules)
    return checks.findings


def check_reachable(types: list[NodeType], rules: list[Rule], starts: list[int]) -> list[Finding]:
    """Every type is reachable from `starts` (the root, and the types an `observation`
    section's clutter makes); only for a grammar with no other error: a rule dropped for an
    error would make its children look unreachable."""
    checks = _Checks(types, None, False)
    checks.check_reachable(types, rules, starts)
    return checks.findings


class _Checks:
    def __init__(self, types: list[NodeType], base_dir: Path | None, allow_outside: bool) -> None:
        self.names = [t.name for t in types]
        self.base_dir = base_dir
        self.allow_outside = allow_outside
        self.findings: list[Finding] = []

    def error(self, loc: Loc, message: str) -> None:
        self.findings.append(("error", loc, message))

    def warn(self, loc: Loc, message: str) -> None:
        self.findings.append(("warning", loc, message))

    def check_root_not_produced(self, rules: list[Rule], root: int | None) -> None:
        for r in rules:
            if r.child == root:
                name = self.names[root]
                self.error(
                    (*r.path, "child"), f"the root type '{name}' cannot be produced by a rule"
                )

    def check_labels(self, types: list[NodeType]) -> None:
        """Dataset objects are matched to types by model file and label: both must be unique."""
        owners: dict[tuple[str, str], str] = {}
        for t in types:
            if t.model and not t.observed:
                self.warn(
                    (*t.path, "model"),
                    f"type '{t.name}' is not observed, so its `model` is never exported or matched",
                )
            # each key with where it is: a label's own place in the list, not the `labels` key
            keys = [(("model", t.model), (*t.path, "model"))] if t.model and t.observed else []
            first = {label: k for k, label in reversed(list(enumerate(t.labels)))}
            keys += [(("label", label), (*t.path, "labels", k)) for label, k in first.items()]
            for k, label in enumerate(t.labels):
                if first[label] != k:  # at its second place
                    self.warn((*t.path, "labels", k), f"type '{t.name}' lists a label twice")
            for key, loc in keys:
                if key in owners:
                    self.error(loc, f"{key[0]} '{key[1]}' already names type '{owners[key]}'")
                owners[key] = t.name

    def check_files(self, types: list[NodeType]) -> None:
        """Mesh and model files are named relative to the grammar file and must stay in its
        directory (see `load_grammar`).  A missing mesh is worth a warning; models are names
        for matching dataset objects too, and are not expected to exist here."""
        for t in types:
            if isinstance(t.geometry, dsl.MeshG):
                loc = (*t.path, "geometry", "mesh", "file")
                mesh = self.file_reference(t.geometry.mesh.file, "mesh file", loc)
                if mesh is not None and self.base_dir is not None and not _is_file(mesh):
                    inside = mesh.is_relative_to(self.base_dir.resolve())
                    where = " next to the grammar" if inside else ""
                    name = t.geometry.mesh.file
                    self.warn(loc, f"mesh file '{name}' not found{where} (looked for {mesh})")
            if t.model:
                self.file_reference(t.model, "model file", (*t.path, "model"))

    def file_reference(self, name: str, what: str, loc: Loc) -> Path | None:
        """The file `name` means, or None after reporting why it cannot be used.

        The file is outside the grammar's directory when the path, resolved, is: an absolute
        path elsewhere, a `..` that climbs out, or a symbolic link on the way that points out.
        Without a directory (text compiled on its own) absolute paths and a leading `..` are.
        """
        if "\x00" in name:
            self.error(loc, f"{what} name contains a NUL character")
            return None
        target, place, link = None, "", ""
        if self.base_dir is None:
            outside = os.path.isabs(name) or os.path.normpath(name).split(os.sep)[0] == ".."
        else:
            try:
                base = self.base_dir.resolve()
                target = (self.base_dir / name).resolve()
            except (OSError, RuntimeError) as exc:  # a loop of symbolic links
                self.error(loc, f"cannot resolve {what} '{name}': {exc}")
                return None
            place = f" ({base})"
            outside = not target.is_relative_to(base)
            if outside and Path(os.path.normpath(base / name)).is_relative_to(base):
                link = f" (through a symbolic link, to {target})"
        if outside and not self.allow_outside:
            self.error(
                loc,
                f"{what} '{name}'{link} is outside the grammar's directory{place}; move it "
                "there, or allow it with --allow-outside-files",
            )
            return None
        return target

    def check_recursion(self, types: list[NodeType], rules: list[Rule]) -> None:
        """Every cycle of the type graph must pass through a type with `max_nesting`.

        Strongly connected components find the types on a cycle in linear time (a grammar may
        have thousands of types); a path is searched for only to name a cycle in a message.
        """
        children: dict[int, list[Rule]] = {t.id: [] for t in types}
        for r in rules:
            children[r.parent].append(r)
        bounded = {t.id for t in types if t.max_nesting is not None}
        free = [t.id for t in types if t.id not in bounded]
        loops = _on_cycles(free, children)  # cycles of types without a bound
        on_cycle: set[int] = set()
        reported = 0
        for t in types:
            if t.id not in loops or t.id in on_cycle or reported >= MAX_CYCLES_REPORTED:
                continue
            cycle = _find_cycle(t.id, children, loops[t.id])
            if cycle is None:  # cannot happen: t is on a cycle of its component
                continue
            on_cycle.update(r.parent for r in cycle)
            reported += 1
            names = " -> ".join([self.names[r.parent] for r in cycle] + [self.names[t.id]])
            self.error(
                (*cycle[-1].path, "child"),
                f"unbounded recursion {names}; set `max_nesting` on one of these types",
            )
        recursive = _on_cycles([t.id for t in types], children)
        for t in types:
            if t.id in bounded and t.id not in recursive:
                self.warn(
                    (*t.path, "max_nesting"),
                    f"type '{t.name}' is not recursive, so `max_nesting` has no effect",
                )

    def check_reachable(self, types: list[NodeType], rules: list[Rule], starts: list[int]) -> None:
        seen, stack = set(starts), list(starts)
        kids: dict[int, list[int]] = {}
        for r in rules:
            kids.setdefault(r.parent, []).append(r.child)
        while stack:
            for c in kids.get(stack.pop(), []):
                if c not in seen:
                    seen.add(c)
                    stack.append(c)
        for t in types:
            if t.id not in seen:
                self.warn(t.path, f"type '{t.name}' is unreachable from the root")


def _on_cycles(nodes: list[int], children: dict[int, list[Rule]]) -> dict[int, set[int]]:
    """The types among `nodes` that lie on a cycle through `nodes` only, each mapped to its
    strongly connected component (Tarjan's algorithm, without recursion)."""
    allowed = set(nodes)
    index: dict[int, int] = {}
    low: dict[int, int] = {}
    stack: list[int] = []
    on_stack: set[int] = set()
    out: dict[int, set[int]] = {}
    for root in nodes:
        if root in index:
            continue
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        work = [(root, iter(children[root]))]
        while work:
            node, kids = work[-1]
            for r in kids:
                child = r.child
                if child not in allowed:
                    continue
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(children[child])))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:  # every child done
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    looped = any(r.child == node for r in children[node])
                    if len(component) > 1 or looped:
                        out.update(dict.fromkeys(component, component))
    return out


def _find_cycle(
    start: int, children: dict[int, list[Rule]], allowed: set[int]
) -> list[Rule] | None:
    """Rules of a path start -> ... -> start through `allowed` types, if any (depth first)."""
    via: dict[int, Rule] = {}  # the rule each type was first reached by
    stack = [start]
    seen = {start}
    while stack:
        node = stack.pop()
        for r in children[node]:
            if r.child == start:
                path = [r]
                while node != start:
                    path.append(via[node])
                    node = via[node].parent
                return path[::-1]
            if r.child not in seen and r.child in allowed:
                seen.add(r.child)
                via[r.child] = r
                stack.append(r.child)
    return None


def _is_file(path: Path) -> bool:
    """`path.is_file()`, False for a name the system refuses (too long, a loop of links)."""
    try:
        return path.is_file()
    except (OSError, RuntimeError):
        return False
