"""Instruction-controllable 4D scene generation (paper: Sec. Instruction-controllable 4D Scene Generation): target
cameras, the low-level conditions C_I / C_D projected from the Gaussians, the 4D edits applied before, and the
``gdwm generate`` / ``gdwm edit`` commands. Import the modules themselves: the CLI imports ``cli`` on every start,
so this package's root stays free of torch imports."""
