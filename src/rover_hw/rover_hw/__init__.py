"""The rover's hardware side: the serial protocol, the bridge node, the controller emulator."""

