"""Supervision: what vehicles report about their sessions and the rules applied to it
(``reports``), the periodic rules (``timers``), and what operators watch (``metrics``)."""
