"""World model (frame tokenizer, action-conditioned dynamics, state and success heads): not built yet."""
