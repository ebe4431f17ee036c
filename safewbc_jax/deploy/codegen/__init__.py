"""The deployed step as C99: a closed jaxpr of flat vectors in and out, written as one C
function with static buffers, no malloc and no dependency beyond libm (``emit``), built
with the system C compiler and called on numpy arrays (``build``)."""
