"""Main job: run one scene and write its outputs (DESIGN section 3).

  mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR] [--quiet]
                                          [PETSc options ...]

PETSc options on the command line override the config's [solver] options.  Outputs in
DIR (default: output.dir of the config, else out/<config name>): frames.h5, frames.xdmf,
previews/*.png, contact_sheet.png, frames.usdc (USD for DCC tools), summary.json.
Exit status: 0 done, 2 bad command line or config (reported once, nothing written), 3
the run failed part-way (frames so far and summary.json kept).  All the work is in lc_petsc/batch.py.
"""

import sys

from lc_petsc.batch import main

if __name__ == "__main__":
    sys.exit(main())
