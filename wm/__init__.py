"""World model: frame tokenizer, action-conditioned dynamics, state and success heads (`model`), training
(`train`), imagination (`imagine`), held-out quality (`quality`, `metrics`), the episode judge (`judge`),
its benchmark (`bench`), the comparison of training runs' loss curves (`curves`), and what follows from
the actions by models of the robot: its motion (`egomotion`), what its camera sees then (`fill`,
`geometric`) and the state of an object its hand holds (`grasp`)."""
