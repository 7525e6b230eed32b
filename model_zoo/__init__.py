"""nn.Modules and their variant registry (import ``model_zoo``). Imports no platform code."""
