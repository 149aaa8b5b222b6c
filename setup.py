"""Package layout: the core ``slamkit``, the Hydra configs in ``conf/`` shipped as ``slamkit.conf``, and
each first-party plugin in ``plugins/`` as its own top-level package (registered by entry points exactly
like a third-party plugin). Metadata lives in pyproject.toml.

Data folders (conf/<group>, a plugin's conf/ and vocabularies/) are listed as packages too: setuptools ships
package data only from listed packages and warns about every folder it would otherwise have to guess at."""

from setuptools import find_namespace_packages, find_packages, setup

_SKIP = ["*__pycache__*", "*.egg-info*"]
core = find_packages(include=["slamkit", "slamkit.*"])
conf = ["slamkit.conf", *("slamkit.conf." + p for p in find_namespace_packages("conf", exclude=_SKIP))]
plugins = find_namespace_packages("plugins", exclude=_SKIP)
package_dir = {"slamkit.conf": "conf"}
package_dir.update({p: "plugins/" + p.replace(".", "/") for p in plugins})

setup(
    packages=[*core, *conf, *plugins],
    package_dir=package_dir,
    package_data={
        "slamkit": ["py.typed"],
        **{p: ["*.yaml"] for p in conf},
        **{p: ["py.typed", "*.yaml", "*.skvoc"] for p in plugins},
    },
)
