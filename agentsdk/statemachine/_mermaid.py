"""Mermaid ``stateDiagram-v2`` of a machine class, optionally with the states of a run highlighted."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

from ._declaration import region_names

if TYPE_CHECKING:
    from ._machine import StateMachine

VISITED_STYLE = "fill:#ffd966,stroke:#b45f06,stroke-width:2px"


def render_mermaid(cls: type[StateMachine], visited: Iterable[str] | None = None) -> str:
    """The diagram of ``cls`` (nested machines as composite states); ``visited`` paths get class ``visited``."""
    lines = ["stateDiagram-v2"]
    ids: dict[str, str] = {}
    _into(cls, lines, "    ", "", cls.__name__, ids)
    if visited is not None:
        hit = sorted({ids[p] for p in visited if p in ids})
        lines.append(f"    classDef visited {VISITED_STYLE}")
        if hit:
            lines.append(f"    class {','.join(hit)} visited")
    return "\n".join(lines) + "\n"


def _into(cls: type[StateMachine], lines: list[str], indent: str, prefix: str, path: str, ids: dict[str, str]) -> None:
    """Append ``cls``'s states and edges; ``ids`` maps each state path to its Mermaid id."""
    spec = cls.definition()

    def sid(name: str) -> str:
        return f"{prefix}{name}"

    for name, st in spec.states.items():
        ids[f"{path}/{name}"] = sid(name)
        notes = []
        if st.timeout is not None:
            notes.append(f"timeout {st.timeout:g}s")
        if st.fault:
            notes.append("fault handler")
        if st.history is not None:
            notes.append(f"{st.history} history")
        if prefix:
            lines.append(f'{indent}state "{name}" as {sid(name)}')
        if st.machine is not None or st.parallel is not None:
            regions = (st.machine,) if st.machine is not None else st.parallel or ()
            tags = region_names(regions)
            lines.append(f"{indent}state {sid(name)} {{")
            for i, (region, tag) in enumerate(zip(regions, tags, strict=True)):
                if i:
                    lines.append(f"{indent}    --")
                lines.append(f"{indent}    %% {region.__name__}")
                inner = f"{sid(name)}__" if st.machine is not None else f"{sid(name)}__{tag}__"
                _into(region, lines, indent + "    ", inner, f"{path}/{name}/{region.__name__}", ids)
            lines.append(f"{indent}}}")
        elif not prefix and not notes:
            lines.append(f"{indent}{name}")
        for note in notes:
            lines.append(f"{indent}{sid(name)} : {note}")
    lines.append(f"{indent}[*] --> {sid(spec.initial)}")
    for e in spec.edges:
        label = e.event if e.guard is None else f"{e.event} [{e.guard_label}]"
        if e.internal:
            label += " (internal)"
        lines.append(f"{indent}{sid(e.source)} --> {sid(e.target)} : {label}")
    for name, st in spec.states.items():
        if st.final:
            lines.append(f"{indent}{sid(name)} --> [*]")
