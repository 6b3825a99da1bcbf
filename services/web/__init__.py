"""The services app's web layer: portal views, the JSON API, WebSocket consumers (session
feeds, relay), rate limits. Thin: it parses, calls services.sessions, and renders."""
