"""``calib export``: a calibration (calibration.json) in the formats robot-audition tools read.

=================  ==========================================================================================
format             what is written
=================  ==========================================================================================
``json``           calibration.json itself (docs/formats.md)
``yaml``           Kalibr-style YAML: one block per array with ``T_ref_array`` (4×4, maps array-frame points into
                   the reference frame), ``quaternion_wxyz``, ``mics``, ``mics_reference``, ``clock``
``pyroomacoustics`` ``.npy`` of shape (3, all mics): the ``R`` argument of ``pyroomacoustics.MicrophoneArray``,
                   reference frame, arrays in calibration order, channels in WAV order
``odas``           a folder with one complete ODAS configuration per array, ``<array>.cfg`` (``calib.pipeline.formats.
                   odas``): ``mu`` = R·m (array-centred, axes of the reference frame, so ODAS's directions come out
                   in the reference frame), ``sigma2`` the mic-position covariance from the rotation's,
                   ``direction`` and the spatial filter the array's z axis
``urdf``           a URDF robot: a link per array and per mic, fixed joints (xyz, rpy)
``tf``             a shell script of ROS 2 ``static_transform_publisher`` commands, reference → each array
=================  ==========================================================================================
"""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from calib.pipeline.formats.odas import to_odas_configs
from calib.pipeline.formats.outputs import check_file_replaceable, write_file
from calib.pipeline.formats.results import REFERENCE, Calibration
from calib.errors import InputError

COMMAND = "calib export"  # the writer recorded in the output's manifest
FORMATS = ("json", "yaml", "pyroomacoustics", "odas", "urdf", "tf")


def _f(v):
    """A float written so that reading it back gives the same double (repr is shortest round-trip)."""
    return repr(float(v))


def to_yaml_dict(cal: Calibration):
    """The Kalibr-style mapping: ``calib`` (frame, units, clock) and one block per array."""
    out = {"calib": {"format": "calib-calibration (Kalibr-style export)", "reference_array": cal.reference_array,
                     "speed_of_sound": cal.speed_of_sound, "conventions": cal.document.get("conventions"),
                     "units": cal.document.get("units"), "clock": cal.document.get("clock")}}
    for a, doc in zip(cal.arrays, cal.document["arrays"]):
        out[a.name] = {"T_ref_array": a.matrix.tolist(), "quaternion_wxyz": a.quaternion.tolist(),
                       "mics": None if a.mics is None else a.mics.tolist(),
                       "mics_reference": None if a.mics is None else cal.mics(REFERENCE, a.name).tolist(),
                       "clock": doc["clock"], "std": doc.get("std")}
    return out


def to_yaml(cal: Calibration):
    import yaml  # PyYAML: a dependency for this export (Kalibr's files are YAML)

    return yaml.safe_dump(to_yaml_dict(cal), sort_keys=False, default_flow_style=None, width=120)


def _rpy(rot):
    """URDF roll, pitch, yaw (fixed axes x, y, z: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return rot.as_euler("xyz")


def to_urdf(cal: Calibration, robot="calib_arrays"):
    root = ET.Element("robot", name=robot)
    ref = cal.reference_array
    ET.SubElement(root, "link", name=ref)
    for a in cal.arrays:
        if a.name != ref:
            ET.SubElement(root, "link", name=a.name)
            j = ET.SubElement(root, "joint", name=f"{ref}_to_{a.name}", type="fixed")
            ET.SubElement(j, "parent", link=ref)
            ET.SubElement(j, "child", link=a.name)
            ET.SubElement(j, "origin", xyz=" ".join(_f(v) for v in a.position),
                          rpy=" ".join(_f(v) for v in _rpy(a.rotation)))
        for k, m in enumerate([] if a.mics is None else a.mics):
            mic = f"{a.name}_mic{k}"
            ET.SubElement(root, "link", name=mic)
            j = ET.SubElement(root, "joint", name=f"{a.name}_to_{mic}", type="fixed")
            ET.SubElement(j, "parent", link=a.name)
            ET.SubElement(j, "child", link=mic)
            ET.SubElement(j, "origin", xyz=" ".join(_f(v) for v in m), rpy="0 0 0")
    ET.indent(root)
    return '<?xml version="1.0"?>\n<!-- calib: arrays and mics (one link per WAV channel) -->\n' + \
        ET.tostring(root, encoding="unicode") + "\n"


def to_tf(cal: Calibration):
    lines = ["#!/bin/sh", "# ROS 2 static transforms from calib: the reference array's frame to each array's frame",
             "# (translation m; rotation as a quaternion, given by name: ROS is scalar-last).", ""]
    for a in cal.arrays:
        if a.name == cal.reference_array:
            continue
        x, y, z = (_f(v) for v in a.position)
        qw, qx, qy, qz = (_f(v) for v in a.quaternion)
        lines.append(f"ros2 run tf2_ros static_transform_publisher --x {x} --y {y} --z {z} --qx {qx} --qy {qy} "
                     f"--qz {qz} --qw {qw} --frame-id {cal.reference_array} --child-frame-id {a.name} &")
    lines.append("wait")
    return "\n".join(lines) + "\n"


def export(cal: Calibration, fmt, path, inputs=()):
    """Write ``cal`` in format ``fmt`` (one of :data:`FORMATS`) to ``path`` (atomic). Returns the path.

    The output policy applies (pipeline/formats/outputs.py): ``path`` may not be one of ``inputs`` (the
    calibration read), and an existing file is replaced only if calib wrote it (and it is unedited)."""
    path = Path(path)
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}: one of {', '.join(FORMATS)}")
    unknown = [a.name for a in cal.arrays if not np.isfinite(a.position).all()]
    if unknown:
        where = f"{Path(inputs[-1])}: " if inputs else ""
        raise InputError(f"{where}no position for array(s) {', '.join(unknown)}: the calibration failed (its "
                         "report.json says why); nothing to export")
    missing = [a.name for a in cal.arrays if a.mics is None]
    if missing and fmt in ("pyroomacoustics", "odas", "urdf"):
        raise InputError(f"{fmt} export needs the mic geometry; none for {', '.join(missing)} "
                         "(features/meta.json without 'mics': re-run `calib features`)")
    if fmt == "odas":
        return _export_odas(cal, path, inputs)
    check_file_replaceable(path, inputs, command=COMMAND)  # before the work
    if fmt == "pyroomacoustics":
        import io as _io

        buf = _io.BytesIO()
        np.save(buf, cal.mics(REFERENCE).T)
        data = buf.getvalue()
    else:
        data = {"json": lambda c: json.dumps(c.document, indent=2) + "\n", "yaml": to_yaml,
                "urdf": to_urdf, "tf": to_tf}[fmt](cal)
    return write_file(path, data, command=COMMAND, inputs=inputs)


def _export_odas(cal, path, inputs):
    """One ODAS configuration per array, ``path/<array>.cfg`` (ODAS runs one array per process); each file
    under the output policy, all checked before any is written."""
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: exists and is not a folder (the odas export writes one <array>.cfg per array)")
    configs = to_odas_configs(cal)
    bad = [n for n in configs if Path(n).name != n or n in (".", "..")]
    if bad:
        raise InputError(f"odas export: array name {bad[0]!r} cannot name a file <array>.cfg")
    configs = {path / f"{name}.cfg": text for name, text in configs.items()}
    for p in configs:
        check_file_replaceable(p, inputs, command=COMMAND)
    for p, text in configs.items():
        write_file(p, text, command=COMMAND, inputs=inputs)
    return path
