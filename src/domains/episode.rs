//! An episode's running totals (return, discounted return, mean forecast), kept the same way by
//! training, evaluation and the simulator client.

use super::Transition;

#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeTotals {
    pub steps: u64,
    /// Sum of rewards.
    pub ret: f64,
    /// Sum of gamma^t * reward.
    pub discounted: f64,
    /// The task ended it (a walker fell, the lander landed or crashed), not the step limit.
    pub terminated: bool,
    gamma: f64,
    discount: f64,
    forecast_sum: f64,
}

impl EpisodeTotals {
    pub fn new(gamma: f64) -> EpisodeTotals {
        EpisodeTotals {
            steps: 0,
            ret: 0.0,
            discounted: 0.0,
            terminated: false,
            gamma,
            discount: 1.0,
            forecast_sum: 0.0,
        }
    }

    /// Adds one step, whose action had forecast `f_t` (1 for a policy without a plan); true when
    /// the step ended the episode.
    pub fn record(&mut self, transition: &Transition, f_t: u64) -> bool {
        self.steps += 1;
        self.ret += transition.reward;
        self.discounted += self.discount * transition.reward;
        self.discount *= self.gamma;
        self.forecast_sum += f_t as f64;
        self.terminated = transition.terminated;
        transition.terminated || transition.truncated
    }

    /// The paper's episode forecast: the mean of f_t over the steps (NaN before the first).
    pub fn forecast(&self) -> f64 {
        self.forecast_sum / self.steps as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn totals_discount_each_reward_by_its_step() {
        let mut totals = EpisodeTotals::new(0.5);
        let step = |reward, terminated| Transition {
            reward,
            terminated,
            truncated: false,
        };
        assert!(!totals.record(&step(2.0, false), 1));
        assert!(!totals.record(&step(4.0, false), 2));
        assert!(totals.record(&step(8.0, true), 6));
        assert_eq!(totals.steps, 3);
        assert_eq!(totals.ret, 14.0);
        assert_eq!(totals.discounted, 2.0 + 0.5 * 4.0 + 0.25 * 8.0);
        assert!(totals.terminated);
        assert_eq!(totals.forecast(), 3.0);
    }
}
