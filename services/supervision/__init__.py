"""Supervision: what vehicles report about their sessions and the rules applied to it
(``reports``, fleet's vehicle-events listener), what a live session's situation is
(``situation``), the periodic rules (``timers``), and what operators watch
(``metrics``)."""
