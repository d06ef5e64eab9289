"""Main job: run one scene and write its outputs (DESIGN section 3).

  mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR] [--quiet]
                                          [--restart CHECKPOINT|latest] [--force]
                                          [PETSc options ...]

PETSc options on the command line override the config's [solver] options.  Outputs in
DIR (default: output.dir of the config, else out/<config name>): frames.h5, frames.xdmf,
previews/*.png, contact_sheet.png, frames.usdc (USD for DCC tools), summary.json.  Exit
status: 0 done, 2 bad command line, config or scene, or the output folder is in use by
another run (reported once, nothing changed), 3 the run failed part-way (frames so far
and summary.json kept), 75 stopped by SIGTERM/SIGUSR1/SIGINT after a checkpoint, or during
the set-up (nothing written; under mpiexec send SIGUSR1 to mpiexec: README, "Checkpoints and
restart").  All the work is in lc_petsc/batch.py and lc_petsc/job.py.
"""

from lc_petsc.batch import exit_process, main

if __name__ == "__main__":
    exit_process(main())
