"""The team stack's servers, one class each behind one protocol (`base.Server`: launch, start, ready,
running, stop), which `pipeline.team.stack.Stack` composes."""
