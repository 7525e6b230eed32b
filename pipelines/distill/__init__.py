"""Foundation-feature distillation into the reconstructed Gaussians (paper: Foundation-feature Gaussian Tokenizer)."""
