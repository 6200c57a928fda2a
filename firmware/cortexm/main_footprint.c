/*
 * main_footprint.c - the smallest image that links everything the PX4 module
 * runs: the traffic table, the heading state and one covey_guidance_step (decision
 * hold + covey_command + the separation filter) on a static scratch. arm-none-eabi-size of this ELF is the flash and RAM the policy costs
 * an autopilot (weights, code, libm, table, scratch).
 */
#include "covey_guidance.h"
#include "covey_traffic.h"
#include "semihost.h"

static covey_guidance_scratch_t scratch;
static covey_hold_t hold;
static covey_traffic_t traffic;
static covey_heading_t heading;

int main(void)
{
    const covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    const covey_goal_t goal = {10.0f, 0.0f};
    const covey_vehicle_t other = {5.0f, 1.0f, 3.0f, 0u};
    covey_traffic_init(&traffic);
    covey_traffic_put_track(&traffic, 1u, &other, -1.0f, 0.0f);
    covey_traffic_prune(&traffic, 0u, cfg.max_neighbour_age_us);
    const covey_vehicle_t own = {0.0f, 0.0f, covey_heading_for_goal(&heading, 0.0f, 0.0f, &goal), 0u};
    const covey_guidance_config_t gcfg = covey_guidance_defaults(&cfg);
    const float own_vel[2] = {0.0f, 0.0f};
    covey_guidance_out_t out;
    covey_hold_reset(&hold);
    covey_status_t st = covey_guidance_step(&gcfg, &hold, &own, own_vel, &goal, traffic.report,
                                            &traffic.vel_m_s[0][0], traffic.n, 0u, &scratch, &out);
    covey_heading_after_command(&heading, &out.command);
    return (int)st;
}
