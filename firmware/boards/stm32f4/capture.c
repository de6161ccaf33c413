#include "capture.h"

#include "regs.h"

void capture_init(void)
{
    TIM2_PSC = 0;
    TIM2_ARR = 0xFFFFFFFFu;
    /* CC1S = CC2S = 01 (input capture from TI1, TI2), input filter 0011 (8 samples at 84 MHz: ~95 ns) */
    TIM2_CCMR1 = (1u << 0) | (3u << 4) | (1u << 8) | (3u << 12);
    /* CC1 enabled on the rising edge, CC2 enabled on the falling edge (CC2P) */
    TIM2_CCER = (1u << 0) | (1u << 4) | (1u << 5);
    TIM2_EGR = 1u;
    TIM2_CR1 = 1u;
}

capture capture_take(void)
{
    capture c = {0};
    uint32_t sr = TIM2_SR;
    c.t_edge = (sr & TIM_SR_CC2IF) ? TIM2_CCR2 : TIM2_CNT;   /* reading CCRx clears CCxIF */
    if (sr & TIM_SR_CC1IF) {
        c.pps = 1;
        c.t_pps = TIM2_CCR1;
        c.pps_overcapture = (sr & TIM_SR_CC1OF) != 0;
        TIM2_SR = ~TIM_SR_CC1OF;    /* rc_w0: writing 0 clears, 1 leaves */
    }
    return c;
}
