"""An overhead crane for nmpc_avoid_ros, registered under the entry-point group `nmpc_avoid_ros.models`."""

from pathlib import Path


def crane() -> Path:
    """The model file (a function may also build and return a nmpc_avoid_ros Model itself)."""
    return Path(__file__).with_name("crane.yaml")
