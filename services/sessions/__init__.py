"""Sessions, from the request to the end: matching and reserving vehicles, the signed
vehicle tasks and user grants, the state machine and its hash-chained log, notices, and
the workflow helpers autonomous kinds step with. Nothing here imports supervision, the
web layer or a kind (import-linter: "services-acyclic")."""
