"""A plugin module that implements no slamkit hook."""


def components() -> list[str]:
    return ["not a hook"]
