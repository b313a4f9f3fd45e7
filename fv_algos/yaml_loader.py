"""The YAML reader of scene, launch and parameter text: PyYAML's safe loader, with numbers as YAML 1.2
writes them."""
from __future__ import annotations

import re

import yaml


class YamlLoader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2's floats without a dot (1e9, -2E-3) as numbers: YAML 1.1,
    PyYAML's, reads them as text, so `fps:=1e9` was refused as "not of type float"."""


YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9]+[eE][-+]?[0-9]+$"),
                                 list("-+0123456789"))
