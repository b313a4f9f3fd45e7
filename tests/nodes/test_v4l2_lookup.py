"""V4L2 devices found by name, as in /sys/class/video4linux: one capture node per camera, the
metadata node of the same name skipped, and a clear refusal that lists the devices when none
or several match: none is a camera not there yet (SourceMissing: its node exits TEMPFAIL and a
launch waits for it), several a configuration to make more precise."""
from __future__ import annotations

from pathlib import Path

import pytest

from nodes.camera_sources import SourceError, SourceMissing, V4L2Source, find_v4l2_device


def _sysfs(root: Path, devices: dict[str, tuple[str, int]]) -> Path:
    """A fake /sys/class/video4linux: {"video0": (name, index)}."""
    for node, (name, index) in devices.items():
        (root / node).mkdir(parents=True)
        (root / node / "name").write_text(name + "\n")
        (root / node / "index").write_text(f"{index}\n")
    return root


MINI_A = "GelSight Mini R0B 2BKR-4VEE: Ge"
MINI_B = "GelSight Mini R0B 28G8-PVJ5: Ge"


def test_the_capture_node_of_the_named_camera_is_found(tmp_path: Path) -> None:
    sysfs = _sysfs(tmp_path, {"video0": ("Integrated Webcam", 0), "video1": ("Integrated Webcam", 1),
                              "video2": (MINI_A, 0), "video3": (MINI_A, 1)})
    assert find_v4l2_device("GelSight Mini", sysfs) == "/dev/video2"
    assert find_v4l2_device("gelsight mini", sysfs) == "/dev/video2"  # case does not matter


def test_two_sensors_are_told_apart_by_serial_and_refused_by_the_common_name(tmp_path: Path) -> None:
    sysfs = _sysfs(tmp_path, {"video2": (MINI_A, 0), "video3": (MINI_A, 1),
                              "video10": (MINI_B, 0), "video11": (MINI_B, 1)})
    assert find_v4l2_device("28G8-PVJ5", sysfs) == "/dev/video10"
    with pytest.raises(SourceError, match=r"2 cameras match \(/dev/video2, /dev/video10\); give more of the name") as err:
        find_v4l2_device("GelSight Mini", sysfs)
    assert not isinstance(err.value, SourceMissing)  # the name must say which: a configuration error, not a wait


def test_a_camera_not_plugged_in_is_refused_with_the_devices_seen(tmp_path: Path) -> None:
    sysfs = _sysfs(tmp_path, {"video0": ("Integrated Webcam", 0)})
    with pytest.raises(SourceMissing, match=r"no camera of that name \(plugged in\?\)\. Devices: /dev/video0 \(Integrated Webcam\)"):
        find_v4l2_device("GelSight Mini", sysfs)
    with pytest.raises(SourceMissing, match="Devices: none"):
        find_v4l2_device("GelSight Mini", tmp_path / "absent")


def test_a_source_named_by_a_camera_absent_from_this_machine_fails_to_open_by_name() -> None:
    source = V4L2Source("No Such Tactile Camera 0000", 0, 0, 25.0, -1.0, -1.0)
    with pytest.raises(SourceMissing, match="v4l2 'No Such Tactile Camera 0000': no camera of that name"):
        source.open()


@pytest.mark.parametrize("width, height", [(0, 480), (640, 0), (-1, 480)])
def test_a_capture_size_given_by_half_is_refused(width: int, height: int) -> None:
    from nodes.camera import CameraParams
    with pytest.raises(ValueError, match=f"capture size {width}x{height}: both > 0, or both 0"):
        CameraParams(source="v4l2", path="GelSight Mini", width=width, height=height)
    assert CameraParams(source="v4l2", path="GelSight Mini", width=0, height=0).width == 0
