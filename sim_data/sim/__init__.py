"""The simulator: the robot (robot), the home scene (scene, assets/home.xml), the tasks (tasks), two
physics engines (engines: MuJoCo's C engine, MJX), the functional environment (env: reset, step),
the JAX renderer (render), batched episodes (rollout) and the Gymnasium wrapper (gym_env)."""
