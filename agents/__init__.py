"""IoUV vehicle agent: protocol, runtime, control server, adapters and simulators."""
