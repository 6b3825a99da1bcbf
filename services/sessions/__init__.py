"""Sessions, from the request to the end: the request (``request``), opening
(``opening``), matching and reserving vehicles (``matching``, ``feasibility``), the signed
vehicle tasks and user grants (``deployment``, ``signing``, ``ice``), ending (``ending``),
the state machine (``states``) and its hash-chained log (``log``, ``words``, ``feed``),
the recorded video, converted and chained into that log once the session ends
(``video``), notices, reads for pages (``selectors``) and the workflow helpers
autonomous kinds step with (``workflow``). Nothing here imports supervision, the web
layer or a kind (import-linter: "services-acyclic", "core-names-no-kind")."""
