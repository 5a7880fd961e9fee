use crate::config::WorldConfig;
use anyhow::Result;
use pbrl_common::Trajectory;
pub fn render(_t: &Trajectory, _c: &WorldConfig, _n: &str, _p: &std::path::Path) -> Result<()> {
    anyhow::bail!("todo")
}
