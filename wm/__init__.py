"""World model: frame tokenizer, action-conditioned dynamics, state and success heads (`model`), training
(`train`), imagination (`imagine`), held-out quality (`quality`, `metrics`), the episode judge (`judge`),
its benchmark (`bench`) and the comparison of training runs' loss curves (`curves`)."""
