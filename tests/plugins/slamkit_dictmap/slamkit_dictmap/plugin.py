"""Registers ``map=dict`` through the ``slamkit`` entry-point group, as any third party would."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="map",
            name="dict",
            target="slamkit_dictmap.store.DictMapStore",
            config={"covisibility_min_shared": 15},
            description="a minimal map store on plain dicts, one mutex (example third-party plugin)",
        )
    ]
