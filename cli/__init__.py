"""The ``magstack`` command: one thin module per sub-command (parse, call one library function,
print text or ``--json``) and the demo orchestrator. Top of the dependency graph."""
