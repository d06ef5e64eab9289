"""Outputs of the main job (DESIGN section 3): ``frames.h5`` written collectively by all
ranks, ``frames.xdmf`` for ParaView, ``summary.json`` and the report on stdout, PNG
previews and a contact sheet."""

from lc_petsc.io.frames import FramesWriter
from lc_petsc.io.frames_read import read_frames
from lc_petsc.io.summary import format_report, write_summary
from lc_petsc.io.xdmf import write_xdmf

__all__ = ["FramesWriter", "read_frames", "format_report", "write_summary", "write_xdmf"]
