"""Experiments over the world model and the simulator: policy evaluation against the simulator
(`evaluate`), rankings by an ensemble of world models (`ensemble`), their statistics (`stats`), the
HTML report (`report`), sweeps (`sweep`), the body-in-place measurement (`body_in_place`) and the
`make demo` / `make full` chain (`pipeline`) and its timing table with each process's compiling (`timing`)."""
