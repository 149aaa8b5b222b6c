"""Entry point of the slamkit_dbow plugin: declares ``place=dbow`` and its default config node."""

from __future__ import annotations

from typing import Any

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="place",
            name="dbow",
            target="slamkit_dbow.recognizer.DbowPlaceRecognizer",
            config={
                # "builtin": slamkit's own vocabulary (k=10, L=4, trained on its synthetic world);
                # or a path: ORB-SLAM's ORBvoc.txt (DBoW2 text, .txt/.txt.gz) or a slamkit .skvoc file
                "vocabulary": "builtin",
                "direct_index_level": 2,  # ORB-SLAM: L=6 vocabulary, direct index 4 levels up = depth 2
                "min_common_ratio": 0.8,  # ORB-SLAM KeyFrameDatabase: candidates share > 80% of max common words
                "group_min_ratio": 0.75,  # ORB-SLAM III-E: keep covisibility groups above 75% of the best
                "n_covisible": 10,  # ORB-SLAM KeyFrameDatabase: a group is a keyframe and its 10 best covisible
            },
            description="DBoW2 bag of binary words + ORB-SLAM's keyframe database (III-E)",
        ),
    ]


@hookimpl
def slamkit_cli_commands(subparsers: Any) -> None:
    """``slamkit vocab train|convert|info|eval``."""
    from slamkit_dbow.cli import add_vocab_parser

    add_vocab_parser(subparsers)
