"""World model: frame tokenizer, action-conditioned dynamics, state and success heads (`model`), training
(`train`), imagination (`imagine`), evaluation (`evaluate`, `metrics`, `judge`), its benchmark (`bench`)
and the comparison of training runs' loss curves (`curves`)."""
