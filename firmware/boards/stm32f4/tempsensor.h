/* The MCU's internal temperature sensor on ADC1 channel 16, converted with the factory calibration
 * (TS_CAL1 at 30 degC, TS_CAL2 at 110 degC): the board's temperature, near the sensors. Non-blocking: the
 * sampling interrupt calls tempsensor_step(), which reads a finished conversion and starts the next. */
#ifndef FW_TEMPSENSOR_H
#define FW_TEMPSENSOR_H

#include <stdint.h>

void tempsensor_init(void);

/* Returns 1 and the latest temperature (centi-degrees C) once one has been converted. */
int tempsensor_step(int16_t *temp_cc);

#endif
