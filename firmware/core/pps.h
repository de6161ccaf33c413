/* PPS latch arithmetic on a free-running 32-bit timer (ticks wrap modulo 2^32).
 *
 * The timer captures each sample-clock edge (the ADC's data-ready) and the PPS edge. Sample k's period is
 * (t_prev, t_edge], the edges of samples k-1 and k; a PPS captured at t_pps inside it is latched as
 *     latch = floor((t_pps - t_prev) * 65536 / (t_edge - t_prev)),  at most 65535,
 * the edge's position in 1/65536 of that period (docs/daq-protocol.md: k_edge = k - 1 + latch / 65536).
 * Dividing by the measured period makes the latch independent of the timer's own clock rate: only the
 * ratio of two intervals of the same timer is used. */
#ifndef FW_PPS_H
#define FW_PPS_H

#include <stdint.h>

typedef enum {
    FW_PPS_IN = 0,      /* 0 < t_pps - t_prev <= t_edge - t_prev: the edge lies in this period */
    FW_PPS_LATER = 1,   /* after t_edge (captured before the data-ready interrupt ran): the next period's */
    FW_PPS_STALE = 2,   /* at or before t_prev: too old to latch */
} fw_pps_where;

fw_pps_where fw_pps_locate(uint32_t t_prev, uint32_t t_edge, uint32_t t_pps);

/* The latch of an FW_PPS_IN edge (65535 for an edge on t_edge itself or a zero period). */
uint16_t fw_pps_latch(uint32_t t_prev, uint32_t t_edge, uint32_t t_pps);

#endif
