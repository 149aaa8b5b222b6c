"""Package layout: the core ``slamkit``, the Hydra configs in ``conf/`` shipped as ``slamkit.conf``, and
each first-party plugin in ``plugins/`` as its own top-level package (registered by entry points exactly
like a third-party plugin). Metadata lives in pyproject.toml."""

from setuptools import find_packages, setup

core = find_packages(include=["slamkit", "slamkit.*"])
plugins = find_packages("plugins")
package_dir = {"slamkit.conf": "conf"}
package_dir.update({p: "plugins/" + p.replace(".", "/") for p in plugins})

setup(
    packages=[*core, "slamkit.conf", *plugins],
    package_dir=package_dir,
    package_data={
        "slamkit": ["py.typed"],
        "slamkit.conf": ["*.yaml", "*/*.yaml", "*/*/*.yaml"],
        **{p: ["py.typed", "*.yaml", "conf/*.yaml", "vocabularies/*.skvoc"] for p in plugins},
    },
)
