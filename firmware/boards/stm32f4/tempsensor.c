#include "tempsensor.h"

#include "regs.h"

static int have;
static int16_t last_cc;

void tempsensor_init(void)
{
    ADC_CCR = ADC_CCR_ADCPRE_DIV4 | ADC_CCR_TSVREFE;  /* 21 MHz ADC clock; sensor on */
    ADC1_SMPR1 = 7u << 18;                            /* channel 16: 480 cycles (> 10 us, datasheet) */
    ADC1_SQR3 = 16u;
    ADC1_CR2 = ADC_CR2_ADON;
    ADC1_CR2 |= ADC_CR2_SWSTART;
}

int tempsensor_step(int16_t *temp_cc)
{
    if (ADC1_SR & ADC_SR_EOC) {
        int32_t raw = (int32_t)(ADC1_DR & 0xFFFu), cal1 = TS_CAL1, cal2 = TS_CAL2;
        if (cal2 > cal1) {
            last_cc = (int16_t)(3000 + (raw - cal1) * 8000 / (cal2 - cal1));
            have = 1;
        }
        ADC1_CR2 |= ADC_CR2_SWSTART;   /* ~25 us: done long before the next sample */
    }
    *temp_cc = last_cc;
    return have;
}
