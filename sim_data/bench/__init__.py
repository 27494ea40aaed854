"""Benchmarks and checks of the simulator side, each a command (`make bench` runs the first five):

    python -m sim_data.bench.physics        # engines' steps/s (cpu, mjx)
    python -m sim_data.bench.render         # the JAX renderer against MuJoCo's OpenGL renderer
    python -m sim_data.bench.data           # the dataset generator end to end
    python -m sim_data.bench.policy         # the share of a policy's time in a rollout
    python -m sim_data.bench.variants       # MJX scene variants (contacts, solver settings)
    python -m sim_data.bench.compile        # the recorded rollout's compile time, piece by piece
    python -m sim_data.bench.render_check   # renderer against MuJoCo's, per pixel
    python -m sim_data.bench.success_table  # scripted policies' success at several skills
"""
