"""A plugin whose component does not implement the FeatureExtractor protocol (no extract method)."""

from slamkit.hookspecs import ComponentSpec, hookimpl


class NotAnExtractor:
    n_levels = 1
    scale_factor = 1.2

    def detect(self, image: object) -> list[object]:
        return []


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [ComponentSpec("features", "not_an_extractor", "slamkit_broken.wrong_protocol.NotAnExtractor")]
