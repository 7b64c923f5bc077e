"""Live inputs from phones (Record3D over WebRTC, NeRFCapture over DDS) and fake phones for tests."""
