"""Models of common microphone-array boards: mic geometry and the layout of the board's raw recording.

A board's raw recording often has more channels than mics (playback loopback, a processed beam, an unused
slot); :attr:`Board.channels` says which WAV channel (counted from 0) holds each mic, in the order of
:attr:`Board.mics`. ``calib init`` writes both into session.toml (``mics``, ``channels``), so a raw recording
is read as it is, without re-encoding (docs/formats.md).

Sources (named per board in :attr:`Board.source`): the ODAS project's configurations (introlab/odas,
``config/odaslive/*.cfg``: ``mics.mu`` in m and ``mapping.map``, the raw channel of each mic counted from 1)
and the vendors' documentation of the channel layouts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Board:
    """One board model.

    mics : ((M, 3) as tuples) mic positions in m, the board's own frame (x, y in its plane, z up out of it).
    raw_channels : the channel count of the board's raw recording.
    channels : (M,) the raw recording's channel of each mic, counted from 0.
    note : one line for session.toml; source : where the geometry and the channel layout come from.
    nominal : the geometry is not from a published source (measure the board).
    """
    name: str
    mics: tuple
    raw_channels: int
    channels: tuple
    note: str
    source: str
    nominal: bool = False

    def mic_array(self):
        """(M, 3) float ndarray of :attr:`mics`."""
        return np.asarray(self.mics, float)


BOARDS = {b.name: b for b in (
    Board("respeaker-6-circular",
          ((-0.0232, 0.0401, 0.0), (-0.0463, 0.0, 0.0), (-0.0232, -0.0401, 0.0),
           (0.0232, -0.0401, 0.0), (0.0463, 0.0, 0.0), (0.0232, 0.0401, 0.0)),
          8, (0, 1, 2, 3, 4, 5),
          "ReSpeaker 6-Mic Circular Array kit: r = 46.3 mm; raw 8 channels = 6 mics + 2 playback loopback",
          "ODAS config/odaslive/respeaker_6_mic_array.cfg (mics, map 1-6 of nChannels 8); Seeed wiki "
          "(ReSpeaker 6-Mic Circular Array kit: channels 7-8 are the playback loopback)"),
    Board("respeaker-usb-4mic",
          ((-0.032, 0.0, 0.0), (0.0, -0.032, 0.0), (0.032, 0.0, 0.0), (0.0, 0.032, 0.0)),
          6, (1, 2, 3, 4),
          "ReSpeaker USB Mic Array v2.0 (XVF-3000), 6-channel firmware: channel 0 processed, 1-4 raw mics, "
          "5 playback",
          "ODAS config/odaslive/respeaker_usb_4_mic_array.cfg (mics, map 2-5 of nChannels 6); respeaker/"
          "usb_4_mic_array README (6_channels_firmware.bin: channel 0 processed audio, 1-4 the mics' raw data, "
          "5 playback)"),
    Board("minidsp-uma8",
          ((0.0, 0.0, 0.0), (0.0, 0.043, 0.0), (0.037, 0.021, 0.0), (0.037, -0.021, 0.0),
           (0.0, -0.043, 0.0), (-0.037, -0.021, 0.0), (-0.037, 0.021, 0.0)),
          8, (0, 1, 2, 3, 4, 5, 6),
          "miniDSP UMA-8: centre mic + 6 on r = 43 mm; raw 8 channels = 7 mics + 1 unused",
          "ODAS config/odaslive/minidsp.cfg (mics, map 1-7 of nChannels 8)"),
    Board("matrix-voice",
          ((0.0, 0.0, 0.0), (-0.038133, 0.003576, 0.0), (-0.020980, 0.032043, 0.0), (0.011971, 0.036381, 0.0),
           (0.035908, 0.013323, 0.0), (0.032805, -0.019767, 0.0), (0.004999, -0.037972, 0.0),
           (-0.026571, -0.027584, 0.0)),
          8, (0, 1, 2, 3, 4, 5, 6, 7),
          "MATRIX Voice: 8 mics; raw 8 channels, all mics",
          "ODAS config/odaslive/matrix_voice.cfg (mics, map 1-8 of nChannels 8)"),
    Board("respeaker-4-linear",
          ((-0.06, 0.0, 0.0), (-0.02, 0.0, 0.0), (0.02, 0.0, 0.0), (0.06, 0.0, 0.0)),
          8, (0, 1, 2, 3),
          "ReSpeaker 4-Mic Linear Array kit: NOMINAL spacing (4 cm): measure your board; raw 8 channels = "
          "4 mics, 2 unused, 2 playback echo",
          "Seeed wiki (ReSpeaker 4-Mic Linear Array Kit: 8 input channels, only the first 4 valid capture data, "
          "the last 2 the playback echo); spacing nominal (no published coordinates found)",
          nominal=True),
)}
