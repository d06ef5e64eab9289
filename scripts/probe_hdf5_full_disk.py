r"""What libhdf5 does when the disk fills up under h5py (the reason lc_petsc checks the
free space before every HDF5 write, lc_petsc/io/disk.py).

Run as root (it mounts a 2 MB tmpfs and unmounts it again):

  .venv/bin/python scripts/probe_hdf5_full_disk.py            # serial (sec2 driver)
  OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 \\
      timeout 60 mpiexec -n 2 .venv/bin/python scripts/probe_hdf5_full_disk.py --mpio

It grows a chunked dataset frame by frame (30,000 float64 per frame) until a write
fails, prints the exception, then closes the file.  Measured with Debian's HDF5 1.10
(2026-12-02): serial, the 8th frame's flush raises RuntimeError (errno 28), the close
raises "Can't decrement id ref count" and the interpreter segfaults at exit
(H5D_close, exit status 139); with --mpio on 2 ranks one rank fails in H5Dset_extent,
the other in H5Dwrite, and the close hangs (killed by the timeout).
"""

import argparse
import os
import subprocess
import tempfile

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mpio", action="store_true", help="mpio driver (run under mpiexec)")
    args = ap.parse_args()
    import h5py
    from mpi4py import MPI
    comm = MPI.COMM_WORLD
    vol = comm.bcast(tempfile.mkdtemp(prefix="hdf5_full_") if comm.rank == 0 else None)
    if comm.rank == 0:
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", vol], check=True)
    comm.Barrier()
    kw = {"driver": "mpio", "comm": comm} if args.mpio else {}
    try:
        f = h5py.File(os.path.join(vol, "t.h5"), "w", **kw)
        d = f.create_dataset("p", shape=(0, 10000, 3), maxshape=(None, 10000, 3),
                             chunks=(1, 10000, 3), dtype="f8")
        try:
            for k in range(100):
                d.resize(k + 1, axis=0)
                if args.mpio:
                    with d.collective:
                        d[k] = np.full((10000, 3), k, float)
                else:
                    d[k] = np.full((10000, 3), k, float)
                f.flush()
                print(f"rank {comm.rank}: frame {k} written", flush=True)
        except Exception as e:  # noqa: BLE001 - the point of the probe
            print(f"rank {comm.rank}: {type(e).__name__}: {str(e)[:200]}", flush=True)
        try:
            f.close()
            print(f"rank {comm.rank}: closed", flush=True)
        except Exception as e:  # noqa: BLE001
            print(f"rank {comm.rank}: close: {type(e).__name__}: {str(e)[:200]}", flush=True)
    finally:
        if comm.rank == 0:
            subprocess.run(["umount", "-l", vol], check=False)
            os.rmdir(vol)
    print(f"rank {comm.rank}: exiting (a segfault after this line is libhdf5's)", flush=True)


if __name__ == "__main__":
    main()
