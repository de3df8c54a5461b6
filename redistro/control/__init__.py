"""Pure control functions: numpy in, numpy out; no IPC, no clocks, no globals."""
