"""`python -m mpi4py -m nac_onboard.compute ...`: one rank of the MPI job (see runner.py)."""

import sys

from nac_onboard.compute.runner import main

sys.exit(main())
