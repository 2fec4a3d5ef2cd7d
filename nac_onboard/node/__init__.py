"""What a companion computer is (Python, glibc, MPI build, clock, serial port, disk) and what a fleet of them
needs to agree on before an MPI job: the doctor's checks, the MPI hostfile and the MPI-build check."""
