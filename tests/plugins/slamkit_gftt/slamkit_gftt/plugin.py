"""Registers ``features=gftt_orb`` through the ``slamkit`` entry-point group, as any third party would."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="features",
            name="gftt_orb",
            target="slamkit_gftt.extractor.GfttOrbExtractor",
            config={"n_features": 500, "quality_level": 0.01, "min_distance_px": 8.0},
            description="Shi-Tomasi corners described by ORB (example third-party plugin)",
        )
    ]
