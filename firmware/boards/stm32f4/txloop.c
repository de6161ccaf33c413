#include "txloop.h"

#include "regs.h"
#include "usart.h"
#include "vectors.h"

#define USART_DAQ USART1_BASE

#ifdef FW_TX_MAX_HZ
static volatile uint32_t credit;     /* in 1/1000 frames: FW_TX_MAX_HZ added each millisecond */

void systick_handler(void)
{
    if (credit < 4000u)
        credit += FW_TX_MAX_HZ;
}

static int may_send(void)
{
    return credit >= 1000u;
}

static void spend(void)
{
    __asm volatile("cpsid i" ::: "memory");
    credit -= 1000u;
    __asm volatile("cpsie i" ::: "memory");
}

static void pacing_init(uint32_t core_hz)
{
    SYST_RVR = core_hz / 1000u - 1u;
    SYST_CVR = 0;
    SYST_CSR = 7u;    /* processor clock, interrupt, enable */
}
#else
static int may_send(void)
{
    return 1;
}

static void spend(void)
{
}

static void pacing_init(uint32_t core_hz)
{
    (void)core_hz;
}
#endif

void tx_loop(fw_daq *d, uint32_t core_hz)
{
    uint8_t frame[FW_FRAME_SIZE];
    pacing_init(core_hz);
    for (;;) {
        /* sleep with interrupts masked, so that one arriving between the test and the WFI still wakes it */
        __asm volatile("cpsid i" ::: "memory");
        if (!may_send() || fw_ring_fill(&d->ring) == 0u)
            __asm volatile("wfi" ::: "memory");
        __asm volatile("cpsie i" ::: "memory");
        if (may_send() && fw_daq_next_frame(d, frame)) {
            spend();
            usart_write(USART_DAQ, frame, sizeof frame);
        }
    }
}
