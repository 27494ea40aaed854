"""World model: frame tokenizer, action-conditioned dynamics, state and success heads (`model`), training
(`train`), imagination (`imagine`), evaluation (`evaluate`, `metrics`, `judge`) and its benchmark (`bench`)."""
