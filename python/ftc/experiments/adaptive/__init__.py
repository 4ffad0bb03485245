"""The adaptive policy's training (a distribution of degradations, a privileged
teacher, DAgger) and evaluation; the method that flies it is
:mod:`ftc.control.agents.learned.adaptive_policy`. See docs/adaptive.md."""
