#include "daq.h"

#include <string.h>

#include "pps.h"

void fw_daq_init(fw_daq *d)
{
    memset(d, 0, sizeof *d);
    fw_ring_init(&d->ring);
}

void fw_daq_pps(fw_daq *d, uint32_t t_pps)
{
    if (d->pps_pending) {
        d->c.pps_double++;
        return;
    }
    d->t_pps = t_pps;
    d->pps_pending = true;
}

/* Advance the clock edge; the PPS flag and latch of the period that ends at t_edge into s. */
static void clock_edge(fw_daq *d, uint32_t t_edge, fw_sample *s)
{
    s->counter = d->c.samples++;
    s->flags = 0;
    s->latch = 0;
    if (d->pps_pending) {
        /* (before the first edge the period is empty: an edge can only be later or stale) */
        uint32_t t_prev = d->have_prev ? d->t_prev : t_edge;
        fw_pps_where w = fw_pps_locate(t_prev, t_edge, d->t_pps);
        if (w == FW_PPS_IN) {
            s->flags = FW_FLAG_PPS | FW_FLAG_LATCH;
            s->latch = fw_pps_latch(t_prev, t_edge, d->t_pps);
            d->c.pps_edges++;
            d->pps_pending = false;
        } else if (w == FW_PPS_STALE) {
            d->c.pps_stale++;
            d->pps_pending = false;
        }
    }
    d->t_prev = t_edge;
    d->have_prev = true;
}

void fw_daq_sample(fw_daq *d, const int32_t counts[FW_CHANNELS], uint32_t t_edge, bool temp_valid,
                   int16_t temp_cc)
{
    fw_sample s;
    clock_edge(d, t_edge, &s);
    memcpy(s.counts, counts, sizeof s.counts);
    s.temp_cc = temp_valid ? temp_cc : 0;
    if (temp_valid)
        s.flags |= FW_FLAG_TEMP;
    if (fw_ring_push(&d->ring, &s)) {
        d->dropping = false;
        return;
    }
    d->c.dropped++;
    if (!d->dropping)
        d->c.overruns++;
    d->dropping = true;
}

void fw_daq_sample_bad(fw_daq *d)
{
    d->c.samples++;
    d->c.bad_input++;
    d->have_prev = false;
}

bool fw_daq_next_frame(fw_daq *d, uint8_t out[FW_FRAME_SIZE])
{
    fw_sample s;
    if (!fw_ring_pop(&d->ring, &s))
        return false;
    fw_frame_build(&s, out);
    d->c.frames_sent++;
    return true;
}
