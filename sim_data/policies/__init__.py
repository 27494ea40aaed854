"""Policies: what acts in the simulator and in the world model, all of one protocol
(registry.Policy: `init_carry`, `act`, batched and jittable).

- scripted: inverse-kinematics state machines per task with a skill knob, action programs, random play;
- bc: behaviour-cloning networks (image and proprioception -> action chunks), their parameter files;
- degrade: counterfactual families (a policy's actions degraded by noise, latency, grip, drive);
- zoo: training lineages of checkpoints and measuring their success (`python -m sim_data.policies.zoo`);
- registry: policy specs, plug-ins and the zoo's registry, resolved to named sources.
"""
