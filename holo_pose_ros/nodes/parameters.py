"""Node parameters: declared with descriptions (and ranges) in code, their defaults read from the node's YAML in
config/, so every default lives in exactly one place that users can also pass to `--params-file`."""

from __future__ import annotations

import yaml
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from holo_pose_ros.resources import config_dir

# name -> (description, read_only, extra ParameterDescriptor fields such as ranges)
ParameterSpecs = dict[str, tuple[str, bool, dict]]


def load_defaults(file_name: str, node_name: str, specs: ParameterSpecs) -> dict:
    """`node_name: ros__parameters:` of config/<file_name>, or the file's only node section when none has that name
    (a node renamed with `-r __node:=other` keeps its defaults); ValueError unless it names exactly the node's
    parameters, or when the file has several sections and none of `node_name`."""
    path = config_dir() / file_name
    with open(path) as f:
        sections = yaml.safe_load(f)
    if not isinstance(sections, dict) or not sections:
        raise ValueError(f"{path}: expected '<node name>: ros__parameters: ...'")
    if node_name not in sections and len(sections) > 1:
        raise ValueError(f"{path}: no section of node '{node_name}' (has {', '.join(map(str, sections))})")
    section = sections[node_name] if node_name in sections else next(iter(sections.values()))
    defaults = section.get("ros__parameters") if isinstance(section, dict) else None
    if not isinstance(defaults, dict):
        raise ValueError(f"{path}: no 'ros__parameters' mapping")
    if set(defaults) != set(specs):
        raise ValueError(f"{path}: parameters {sorted(set(defaults) ^ set(specs))} are not the node's")
    return defaults


def declare_parameters(node: Node, file_name: str, specs: ParameterSpecs) -> dict:
    """Declare every parameter of `specs` on `node` with its YAML default; returns {name: value} after overrides."""
    defaults = load_defaults(file_name, node.get_name(), specs)
    for name, (description, read_only, extra) in specs.items():
        node.declare_parameter(name, defaults[name], ParameterDescriptor(description=description, read_only=read_only,
                                                                         **extra))
    return {name: node.get_parameter(name).value for name in specs}
