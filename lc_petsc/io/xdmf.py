"""``frames.xdmf``: an XDMF 2 temporal collection of polylines over ``frames.h5``.

One uniform grid per written frame (a row of ``/frame_valid`` False is no frame, and no
grid), all sharing the wisps' "Mixed" polyline topology (``/polylines``) and taking
their points from a hyperslab of ``/positions``; no data is copied.  ParaView opens it
with its XDMF reader ("Xdmf Reader", i.e. XDMF 2); the test suite reads it back with
VTK's ``vtkXdmfReader``.

The first child of each frame's hyperslab item is a comment naming the frame: VTK's XDMF
reader keys its per-block geometry cache on the text of that first child, and without a
unique text there it prints "Cannot find DataItem element in geometry xml, no caching
possible" for every frame (and with a shared text it would return a cached frame).
"""

from __future__ import annotations

import os
from xml.sax.saxutils import quoteattr

from lc_petsc.io.disk import written_aside


def write_xdmf(xdmf_path, h5_path, times, n_vertices, n_wisps, name="frames", valid=None):
    """Write ``xdmf_path`` describing the frames of ``h5_path`` at ``times`` (one per row
    of ``/positions``); rows whose ``valid`` is False (lost, ``/frame_valid``) are left
    out."""
    h5 = os.path.relpath(h5_path, os.path.dirname(os.path.abspath(xdmf_path)) or ".")
    nf, nv = len(times), int(n_vertices)
    n_poly = 2 * int(n_wisps) + nv
    lines = ['<?xml version="1.0" ?>',
             '<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>',
             '<Xdmf Version="2.0">',
             ' <Domain>',
             f'  <Grid Name={quoteattr(name)} GridType="Collection" CollectionType="Temporal">']
    for k, t in enumerate(times):
        if valid is not None and not valid[k]:
            continue
        lines += [
            f'   <Grid Name="frame_{k}" GridType="Uniform">',
            f'    <Time Value="{float(t):.17g}"/>',
            f'    <Topology TopologyType="Mixed" NumberOfElements="{n_wisps}">',
            f'     <DataItem Dimensions="{n_poly}" NumberType="Int" Precision="8" Format="HDF">'
            f'{h5}:/polylines</DataItem>',
            '    </Topology>',
            '    <Geometry GeometryType="XYZ">',
            f'     <DataItem ItemType="HyperSlab" Dimensions="{nv} 3" Type="HyperSlab">'
            f'<!--{h5}:/positions[{k}]-->',
            f'      <DataItem Dimensions="3 3" Format="XML">{k} 0 0 1 1 1 1 {nv} 3</DataItem>',
            f'      <DataItem Dimensions="{nf} {nv} 3" NumberType="Float" Precision="8" '
            f'Format="HDF">{h5}:/positions</DataItem>',
            '     </DataItem>',
            '    </Geometry>',
            '   </Grid>']
    lines += ['  </Grid>', ' </Domain>', '</Xdmf>', '']
    with written_aside(xdmf_path) as tmp, open(tmp, "w") as fh:
        fh.write("\n".join(lines))
