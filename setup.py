"""Package layout (everything else is in pyproject.toml).

The kernel sources, configs and dataset manifests stay at the top of the repository (kernels/, configs/,
data_manifests/, where people look for them) and ship inside the package as ctgs._kernels, ctgs._configs
and ctgs._manifests; ctgs/resources.py finds either layout. setuptools can remap folders only with
package-dir, which pyproject.toml cannot combine with package discovery, hence this file: every folder
is discovered (a new kernel subfolder ships without anyone editing a list), none is listed by hand.
"""

from setuptools import find_namespace_packages, setup

SHIPPED = {"ctgs._kernels": "kernels", "ctgs._configs": "configs", "ctgs._manifests": "data_manifests"}
SKIP = ["__pycache__", "*.__pycache__"]


def packages() -> list[str]:
    """ctgs and its subpackages, plus every folder of the shipped trees under its package name."""
    found = find_namespace_packages(include=["ctgs", "ctgs.*"], exclude=SKIP)
    for package, folder in SHIPPED.items():
        found += [package] + [f"{package}.{sub}" for sub in find_namespace_packages(where=folder, exclude=SKIP)]
    return found


if __name__ == "__main__":  # setuptools' build backend runs this file as __main__
    setup(packages=packages(), package_dir=SHIPPED)
