//! `loopd ros2`: a ROS 2 node between a fleet's camera topics and a loopd server (docs/ros2.md).
//! Images in (raw or compressed, per robot by topic or namespace pattern, with CameraInfo and
//! odometry when given), keyframes to the server over its gRPC API, loop closures out
//! (`loopd_msgs/LoopClosure`, `visualization_msgs/MarkerArray`). The server stays ROS-free:
//! this layer is a client, like `client/`, and the server imports nothing of it.
pub mod bridge;
pub mod keyframes;
pub mod metrics;
pub mod msgs;
pub mod queue;
