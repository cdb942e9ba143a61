"""VTK time series (``bgn.paraview``): the .pvd index orders the frames in time, and each
.vtp frame holds the positions and fields exactly (decoded here from VTK's appended raw
layout: a UInt64 byte count before each array, at the offset its DataArray names)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from bgn.paraview import write_frame, write_series

TYPES = {"Float64": np.float64, "Int32": np.int32}


def read_vtp(path: Path) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """(the Piece's attributes, every DataArray by name, (n,) or (n, 3))."""
    raw = path.read_bytes()
    head, _, data = raw.partition(b'<AppendedData encoding="raw">')
    start = data.index(b"_") + 1
    assert b'header_type="UInt64"' in head and b'byte_order="LittleEndian"' in head
    piece = dict(re.findall(r'(\w+)="([^"]*)"', re.search(rb"<Piece[^>]*>", head)[0].decode()))
    arrays = {}
    for attrs in re.findall(rb"<DataArray ([^>]*)/>", head):
        a = dict(re.findall(r'(\w+)="([^"]*)"', attrs.decode()))
        at = start + int(a["offset"])
        size = int(np.frombuffer(data[at:at + 8], np.uint64)[0])
        values = np.frombuffer(data[at + 8:at + 8 + size], TYPES[a["type"]])
        arrays[a["Name"]] = values.reshape(-1, int(a["NumberOfComponents"])).squeeze(-1) \
            if a["NumberOfComponents"] == "1" else values.reshape(-1, 3)
    return piece, arrays


def test_a_frame_holds_its_points_and_fields_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    pos, vel = rng.normal(size=(5, 2)), rng.normal(size=(5, 2))
    path = write_frame(tmp_path / "f", pos, {"velocity": vel, "type": np.array([0, 1, 1, 0, 2]),
                                            "mass": np.arange(5.0) + 0.5})
    piece, arrays = read_vtp(path)
    assert path.suffix == ".vtp" and piece["NumberOfPoints"] == "5"
    assert piece["NumberOfVerts"] == "5"
    np.testing.assert_array_equal(arrays["points"][:, :2], pos)
    np.testing.assert_array_equal(arrays["points"][:, 2], 0.0)  # 2-D: z = 0
    np.testing.assert_array_equal(arrays["velocity"][:, :2], vel)
    np.testing.assert_array_equal(arrays["type"], [0, 1, 1, 0, 2])
    np.testing.assert_array_equal(arrays["mass"], np.arange(5.0) + 0.5)
    np.testing.assert_array_equal(arrays["connectivity"], np.arange(5))  # one vertex a point
    np.testing.assert_array_equal(arrays["offsets"], np.arange(1, 6))


def test_a_series_indexes_every_frame_in_time(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    positions = rng.normal(size=(4, 3, 3))                      # 3-D
    error = rng.random((4, 3))
    pvd = write_series(tmp_path, "rollout", positions, dt=0.5,
                       fields={"error": error, "radius": np.full(3, 0.1)}, start_time=2.0)
    sets = ET.parse(pvd).getroot().find("Collection").findall("DataSet")
    assert [float(s.get("timestep")) for s in sets] == [2.0, 2.5, 3.0, 3.5]
    for t, s in enumerate(sets):
        _, arrays = read_vtp(pvd.parent / s.get("file"))  # the index names files relatively
        np.testing.assert_array_equal(arrays["points"], positions[t])
        np.testing.assert_array_equal(arrays["error"], error[t])
        np.testing.assert_array_equal(arrays["radius"], 0.1)


def test_a_field_of_the_wrong_length_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="field 'mass'"):
        write_frame(tmp_path / "f", np.zeros((3, 2)), {"mass": np.ones(4)})
    with pytest.raises(ValueError, match="positions"):
        write_series(tmp_path, "x", np.zeros((3, 2)), 0.1)
