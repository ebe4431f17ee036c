"""One robot's controller: measurements in, motor commands out (PIQP), its flat packing and
the count of the kernels it runs."""
