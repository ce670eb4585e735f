"""A JSON file that names its format and version (a model folder's manifest.json, a web bundle's bundle.json): read,
checked against the format and the versions this ctgs reads, every refusal one line that says what to do."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

from ctgs.errors import UserError


@dataclass(frozen=True)
class VersionedJson:
    """One such file. The refusals are str.format templates: `missing` of {folder} and {path}, `unreadable` of
    {path} and {exc}, `other_format` of {path}, `other_version` of {path} and {version}."""

    name: str  # the file's name in its folder
    format: str  # its "format" value
    versions: tuple[int, ...]  # the versions this ctgs reads
    missing: str
    unreadable: str
    other_format: str
    other_version: str

    def read(self, folder: str) -> dict:
        """The file of `folder` as a dict; UserError when it is missing, unreadable, or not a version read here."""
        path = os.path.join(folder, self.name)
        if not os.path.isfile(path):
            raise UserError(self.missing.format(folder=folder, path=path))
        try:
            with open(path) as f:
                data = json.load(f)
        except (OSError, ValueError) as exc:
            raise UserError(self.unreadable.format(path=path, exc=exc)) from exc
        if not isinstance(data, dict) or data.get("format") != self.format:
            raise UserError(self.other_format.format(path=path))
        if data.get("version") not in self.versions:
            raise UserError(self.other_version.format(path=path, version=data.get("version")))
        return data
