//! The robots as data: each one's links, joints, observed feet and alive rule, as PyBullet's
//! pybullet_envs loads its MJCF model. The planar ones are rapier2d bodies (`planar`), the others
//! rapier3d ones (`spatial`).

mod ant;
mod cheetah;
mod hopper;
mod humanoid;
mod walker;

pub(super) use ant::ant;
pub(super) use cheetah::cheetah;
pub(super) use hopper::hopper;
pub(super) use humanoid::humanoid;
pub(super) use walker::walker;
