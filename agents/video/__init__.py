"""Video from the vehicle to browsers over WebRTC, with one encoder shared by all viewers.

The agent's control WebSocket carries the signalling (``docs/video.md``); this package
owns everything after it, one module per responsibility:

* :mod:`agents.video.service`: :class:`~agents.video.service.VideoService` is the camera
  behind every WebRTC connection. The connections themselves are :mod:`agents.rtc`'s,
  one per user, negotiated in one flow (the browser offers, ``webrtc_offer`` ->
  ``webrtc_answer``), and each that asks for video gets the camera with ``attach``.
  The source is polled only while at least one viewer's sender is actually pulling
  frames (a connected peer), and closed (camera released) when the last viewer leaves.
* :mod:`agents.video.encoder`: the vehicle's frames are **encoded once** (VP8, libvpx
  through PyAV) and the resulting ``av.Packet``\\ s are handed to every viewer's
  ``RTCRtpSender``. aiortc's sender packetises a packet without re-encoding it
  (``RTCRtpSender._next_encoded_frame`` calls ``Encoder.pack`` for anything that is not
  an ``av.Frame``, the path ``MediaPlayer(decode=False)`` uses), so the CPU cost of
  video does not grow with the number of viewers. A viewer's picture-loss requests
  (PLI/FIR) are routed to the shared encoder, which then emits a keyframe for everyone.
* :mod:`agents.video.rate`: the encoder's bitrate, picture size and frame rate follow
  the pilot's link (receiver estimates, losses).
* :mod:`agents.video.sources`: where pictures come from: a synthetic camera drawn from
  the vehicle's pose, a V4L2 camera (Raspberry Pi camera, USB webcam), an HTTP MJPEG
  stream (ESP32-CAM), or a mission's sensor (the search mission's thermal camera,
  :mod:`agents.missions.search.video`); ``video_source_create`` builds one from the
  agent's configuration.
* :mod:`agents.video.framecode`: the counter and capture time stamped into synthetic
  frames and read back from decoded ones (what latency is measured by).
* :mod:`agents.video.ice`: which local addresses WebRTC offers, and ICE servers from
  the configuration (shared with :mod:`agents.rtc` and :mod:`agents.sfu`).

Nothing here imports Django: this runs on the vehicle's companion computer.
"""

from __future__ import annotations


class VideoError(Exception):
    """A video request could not be served: bad SDP, unknown peer, no common codec, too
    many viewers, bad source configuration. ``str(exc)`` is a sentence for the client."""
